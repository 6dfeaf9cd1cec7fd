"""`softplc run` as real processes: scan process + Modbus process, Modbus on loopback,
HMI writes reaching the program, SIGTERM stopping both with outputs safe."""

from __future__ import annotations

import functools
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException

from softplc.core.lifecycle import PlcState
from softplc.hmi.map import STATUS_SCAN_COUNT, STATUS_STATE
from tests.support import eventually, free_port

ROOT = Path(__file__).resolve().parents[2]


# Processes take seconds to start on a loaded machine; a probe may spawn mbpoll: 100 ms steps.
wait_for = functools.partial(eventually, timeout_s=20.0, step_s=0.1)


@pytest.fixture
def plc_process(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], int]]:
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--modbus", f"127.0.0.1:{port}",
         "--opcua", "off", "--api", "off", "--state-dir", str(tmp_path),
         "--quiet", "--period", "10ms"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        yield proc, port
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def connect(port: int) -> ModbusTcpClient:
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    wait_for(client.connect, timeout_s=40)  # spawning two processes takes seconds when loaded
    return client


def status_block(client: ModbusTcpClient) -> list[int]:
    reply = client.read_input_registers(1024, count=18, device_id=1)
    assert not reply.isError()
    return list(reply.registers)


def test_run_serves_modbus_applies_hmi_writes_and_stops_safely(
        plc_process: tuple[subprocess.Popen[str], int]) -> None:
    proc, port = plc_process
    client = connect(port)
    try:
        block = wait_for(
            lambda: (b := status_block(client))[STATUS_STATE] == PlcState.RUNNING and b)
        scans = (block[STATUS_SCAN_COUNT] << 16) | block[STATUS_SCAN_COUNT + 1]
        later = wait_for(lambda: (b := status_block(client)) and
                         ((b[STATUS_SCAN_COUNT] << 16) | b[STATUS_SCAN_COUNT + 1]) > scans + 10)
        assert later
        # %MX0.1 is coil 801: an HMI write is journaled and visible after a scan. (Not coil
        # 800, `hold`: that stops the feed, tests/runtime/test_hmi_hold.py.)
        assert not client.write_coil(801, True, device_id=1).isError()
        wait_for(lambda: client.read_coils(801, count=1, device_id=1).bits[0])
        # the conveyor motor m1 (%QX0.0) is driven by the program once a part arrives (t=1 s)
        wait_for(lambda: client.read_coils(0, count=1, device_id=1).bits[0], timeout_s=30)
    finally:
        client.close()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "outputs safe" in out


def test_crash_of_the_modbus_process_does_not_stop_the_scan(
        plc_process: tuple[subprocess.Popen[str], int]) -> None:
    proc, port = plc_process
    client = connect(port)
    before = status_block(client)
    client.close()
    assert proc.stdout is not None
    line = wait_for(lambda: (text := proc.stdout.readline()) and "Modbus process pid" in text
                    and text)
    comm_pid = int(line.split("Modbus process pid", 1)[1].split(",")[0])
    assert comm_pid in _children(proc.pid)
    os.kill(comm_pid, signal.SIGKILL)

    def fresh_block() -> list[int] | None:
        # a connection made while the killed process's socket dies may be reset: reconnect
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        try:
            return status_block(client) if client.connect() else None
        except (OSError, ModbusException):
            return None
        finally:
            client.close()

    after = wait_for(fresh_block, timeout_s=40)  # the supervisor restarts the process
    count = lambda b: (b[STATUS_SCAN_COUNT] << 16) | b[STATUS_SCAN_COUNT + 1]  # noqa: E731
    assert count(after) > count(before)
    assert after[STATUS_STATE] == PlcState.RUNNING
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=30)
    assert proc.returncode == 0


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(stat[1]) == pid:
                found.append(int(entry.name))
    return found


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="Debian's mbpoll is not installed")
def test_mbpoll_reads_the_live_image_and_status_block(
        plc_process: tuple[subprocess.Popen[str], int]) -> None:
    proc, port = plc_process
    connect(port).close()

    def mbpoll(*args: str, values: tuple[str, ...] = ()) -> str:
        done = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(port), "-a", "1", "-0", "-1",
                               *args, "127.0.0.1", *values],
                              capture_output=True, text=True, timeout=10)
        assert done.returncode == 0, done.stderr
        return done.stdout

    state = wait_for(lambda: "[1024]: \t2" in mbpoll("-t", "3", "-r", "1024", "-c", "2"))
    assert state
    assert "[0]:" in mbpoll("-t", "0", "-r", "0", "-c", "4")
    assert "Written 1 references" in mbpoll("-t", "4", "-r", "1024", values=("4321",))  # %MW0
    assert wait_for(lambda: "[1024]: \t4321" in mbpoll("-t", "4", "-r", "1024", "-c", "1"))
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=30)


def test_run_with_modbus_writes_none_refuses_every_write(tmp_path: Path) -> None:
    """`--modbus-writes none` reaches the slave: a write is refused with exception 02 and the
    image keeps its value, while reads go on."""
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--modbus", f"127.0.0.1:{port}",
         "--opcua", "off", "--api", "off", "--state-dir", str(tmp_path),
         "--quiet", "--modbus-writes", "none"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        client = connect(port)
        try:
            wait_for(lambda: status_block(client)[STATUS_STATE] == PlcState.RUNNING)
            reply = client.write_coil(800, True, device_id=1)
            assert reply.isError() and reply.exception_code == 2
            time.sleep(0.1)
            assert client.read_coils(800, count=1, device_id=1).bits[0] is False
        finally:
            client.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
