"""Writes on the plain Modbus TCP port in the audit trail, against a real `softplc run` with
a real pymodbus client (issue 31): who (the peer, the role the write policy gives), what
(table, address, IEC address, values), the outcome (applied, or refused with its exception
code); a setpoint written in a burst gives a bounded number of records whose counts add up,
the counts still open are written when the PLC stops, and `softplc audit --verify` passes.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from pymodbus.client import ModbusTcpClient

from softplc.api.client import ApiClient
from softplc.hmi.coalesce import WINDOW_S
from tests.support import eventually, free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
BURST = 200


def softplc(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *argv], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def modbus_records(where: Path) -> list[dict[str, Any]]:
    shown = softplc("audit", "--json", "--state-dir", "state", cwd=where)
    assert shown.returncode == 0, shown.stderr
    return [r for r in map(json.loads, shown.stdout.splitlines()) if r["iface"] == "modbus"]


def test_plain_modbus_writes_are_audited_and_a_burst_is_bounded(tmp_path: Path) -> None:
    modbus_port, api_port = free_port(), free_port()
    api = ApiClient(f"http://127.0.0.1:{api_port}", timeout_s=10)
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--start", "--modbus",
                      f"127.0.0.1:{modbus_port}", "--api", f"127.0.0.1:{api_port}",
                      "--opcua", "off", "--state-dir", "state", "--quiet"],
                     lambda: api.status()["state"] == "RUNNING", cwd=tmp_path,
                     stdout=subprocess.DEVNULL):
        client = ModbusTcpClient("127.0.0.1", port=modbus_port, timeout=5, retries=0)
        assert eventually(client.connect, 30, "the slave accepts the client")
        try:
            assert not client.write_coil(800, True, device_id=1).isError()  # hold, %MX0.0
            # FC6 cannot write half of %MD0: refused with 02, nothing journaled.
            assert client.write_register(2048, 7, device_id=1).exception_code == 2
            started = time.monotonic()
            for n in range(BURST):  # an HMI writing a setpoint as fast as it can
                assert not client.write_register(1028, n, device_id=1).isError()  # %MW4
            burst_s = time.monotonic() - started
        finally:
            client.close()
        eventually(lambda: api.read_symbol("hold") is True, 10, "hold written")
        # The first write of each is in the trail at once, while the PLC runs.
        eventually(lambda: {r["detail"].get("iec") for r in modbus_records(tmp_path)}
                   >= {"%MX0.0", "%MD0", "%MW4"}, 20, "the first writes recorded")
    records = modbus_records(tmp_path)  # after the stop: the counts still open are written
    assert all(r["peer"] == "127.0.0.1" and r["user"] is None and r["role"] == "operator"
               and r["action"] == "write" and r["detail"]["policy"] == "open"
               for r in records)
    hold = [r for r in records if r["detail"].get("iec") == "%MX0.0"]
    assert [(r["outcome"], r["status"], r["detail"]["table"], r["detail"]["address"],
             r["detail"]["values"], r["detail"]["writes"]) for r in hold] == [
        ("applied", 0, "coils", 800, [1], 1)]
    refused = [r for r in records if r["detail"].get("iec") == "%MD0"]
    assert [(r["outcome"], r["status"]) for r in refused] == [("refused", 2)]
    burst = [r for r in records if r["detail"].get("iec") == "%MW4"]
    # One record at the first write, one per window the burst reached, one at the stop.
    assert 2 <= len(burst) <= 2 + math.ceil(burst_s / WINDOW_S), (len(burst), burst_s)
    assert sum(r["detail"]["writes"] for r in burst) == BURST
    assert burst[0]["detail"]["values"] == [0] and burst[-1]["detail"]["values"] == [BURST - 1]
    assert burst[-1]["detail"]["changed"] == burst[-1]["detail"]["writes"]
    verified = softplc("audit", "--verify", "--state-dir", "state", cwd=tmp_path)
    assert verified.returncode == 0 and "audit trail ok" in verified.stdout, verified.stderr
    shown = softplc("audit", "--state-dir", "state", cwd=tmp_path)
    assert "-/operator@127.0.0.1 modbus: write -> refused (2)" in shown.stdout
