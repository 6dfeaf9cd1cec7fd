"""`softplc run` serving a scaled memory setpoint in engineering units (issue 30): the scan
process, its status board and the Modbus process as real processes, an HMI on 127.0.0.1
with the real pymodbus client. The setpoint starts at its `init:`, an HMI write in % reaches
the program as the raw count, and a value the symbol cannot take is exception 03."""

from __future__ import annotations

import functools
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.pdu import ExceptionResponse

from tests.support import eventually, free_port

ROOT = Path(__file__).resolve().parents[2]
WORDS = 1024
IO = """symbols:
  setpoint: {address: '%MW0', type: int, init: 80,
             scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%', modbus: eng}}
  valve:    {address: '%QW0', type: int, driver: none,
             scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%'}}
"""
# The valve follows the setpoint; it is raw on Modbus (the default), the setpoint in %.
PROGRAM = """program: follow
io_image: io.yaml
places: {on: {tokens: 1}}
transitions:
  follow: {read: [on], when: "valve != setpoint", do: ["valve = setpoint"]}
"""
wait_for = functools.partial(eventually, timeout_s=30.0, step_s=0.1)


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], int]]:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "follow.yaml").write_text(PROGRAM, encoding="utf-8")
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "softplc.cli", "run", str(tmp_path / "follow.yaml"), "--start",
         "--modbus", f"127.0.0.1:{port}", "--api", "off", "--opcua", "off",
         "--state-dir", str(tmp_path / "state"), "--quiet", "--period", "10ms"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc, port
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.communicate(timeout=10)


def registers(client: ModbusTcpClient, address: int, count: int) -> list[int] | None:
    reply = client.read_holding_registers(address, count=count, device_id=1)
    return None if reply.isError() else list(reply.registers)


def test_an_hmi_reads_and_writes_the_setpoint_in_percent(
        plc: tuple[subprocess.Popen[str], int]) -> None:
    proc, port = plc
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    wait_for(client.connect, timeout_s=60, what="the Modbus process")
    try:
        # init: 80 %, shown in %; the program copied it into the raw valve: 22118 counts
        wait_for(lambda: registers(client, WORDS, 1) == [80] and registers(client, 0, 1)
                 == [22118], what="the setpoint's init", show=lambda: registers(client, 0, 1))
        assert not client.write_register(WORDS, 55, device_id=1).isError()
        wait_for(lambda: registers(client, 0, 1) == [15206], what="the written setpoint",
                 show=lambda: registers(client, 0, 1))  # 55 % of 27648 = 15206.4
        assert registers(client, WORDS, 1) == [55]
        refused = client.write_register(WORDS, 150, device_id=1)  # raw 41472: beyond an int
        assert isinstance(refused, ExceptionResponse) and refused.exception_code == 3
        assert registers(client, WORDS, 1) == [55]
    finally:
        client.close()
    assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
