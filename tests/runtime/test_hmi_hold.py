"""The HMI demo of the README, end to end: a real `softplc run` of the transport system, a real
pymodbus client writing `hold` (%MX0.0, coil 800), and the HTTP status showing its effect.

While `hold` is 1 conveyor 1 takes no new part on (the part waits at s1_i), the part already on
the belts is still delivered; clearing `hold` resumes the feed.
"""

from __future__ import annotations

import json
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient

from tests.runtime.test_run_process import ROOT, connect, wait_for
from tests.support import eventually_reachable, free_port

HOLD_COIL = 800  # %MX0.0: coils from `bits` (800) are %MX (docs/modbus.md)
S1_I_INPUT = 0  # %IX0.0, discrete input 0: a part waits at conveyor 1's input
PARTS_DELIVERED = 0  # %QW0, holding register 0
# Seed 2 of the transport plant: parts arrive at 1.0 s and 9.2 s, so the second one reaches
# s1_i while `hold` is set, soon after the first has been delivered.
SEED = 2
BELTS = ("c1.moving", "c1.full", "handing_over", "c2.moving", "c2.full")


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], int, int]]:
    modbus, api = free_port(), free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--seed", str(SEED), "--modbus", f"127.0.0.1:{modbus}",
         "--opcua", "off", "--api", f"127.0.0.1:{api}",
         "--state-dir", str(tmp_path), "--quiet", "--period", "10ms"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc, modbus, api
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def status(api: int) -> dict[str, Any]:
    with urllib.request.urlopen(f"http://127.0.0.1:{api}/api/v1/status", timeout=5) as reply:
        document: dict[str, Any] = json.load(reply)
        return document


def waiting_at_input(client: ModbusTcpClient, api: int) -> dict[str, Any] | None:
    """The status while a part waits at s1_i, the belts are empty and conveyor 1 is idle."""
    doc = status(api)
    marking = doc.get("marking", {})
    part_waits = client.read_discrete_inputs(S1_I_INPUT, count=1, device_id=1).bits[0]
    empty = marking.get("c1.idle") == 1 and not any(marking.get(p) for p in BELTS)
    return doc if part_waits and empty else None


def test_hold_stops_the_feed_and_clearing_it_resumes(
        plc: tuple[subprocess.Popen[str], int, int]) -> None:
    proc, modbus, api = plc
    client = connect(modbus)
    # Each service has a process of its own and serves once it is ready: the Modbus slave
    # answering says nothing of the HTTP API (refusing connections while it starts).
    eventually_reachable(lambda: status(api), 60, "the HTTP API answers")
    try:
        assert not client.write_coil(HOLD_COIL, True, device_id=1).isError()
        wait_for(lambda: client.read_coils(HOLD_COIL, count=1, device_id=1).bits[0])
        # The part taken on before the write (if any) is finished: belts empty, a part waiting.
        held = wait_for(lambda: waiting_at_input(client, api), timeout_s=60)
        delivered = client.read_holding_registers(PARTS_DELIVERED, count=1, device_id=1)
        # 100 scans later the waiting part has still not been taken on, and m1 is off.
        later = wait_for(lambda: (d := status(api))["scan_count"] >= held["scan_count"] + 100
                         and d)
        assert later["marking"].get("c1.idle") == 1 and not later["marking"].get("c1.moving")
        assert client.read_discrete_inputs(S1_I_INPUT, count=1, device_id=1).bits[0]
        assert not client.read_coils(0, count=1, device_id=1).bits[0]  # m1 (%QX0.0)
        assert client.read_holding_registers(PARTS_DELIVERED, count=1, device_id=1).registers \
            == delivered.registers
        # Clearing `hold` resumes: the waiting part is taken on, conveyor 1 runs.
        assert not client.write_coil(HOLD_COIL, False, device_id=1).isError()
        wait_for(lambda: status(api)["marking"].get("c1.moving") == 1, timeout_s=30)
        wait_for(lambda: client.read_coils(0, count=1, device_id=1).bits[0], timeout_s=30)
    finally:
        client.close()
    proc.terminate()
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
