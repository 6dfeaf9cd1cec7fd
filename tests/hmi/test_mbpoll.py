"""An independent Modbus master (mbpoll, libmodbus) against the slave, 0-based (-0)."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest

from softplc.core.image import parse_address
from softplc.core.snapshot import HmiWrite
from softplc.hmi.map import STATUS_WORDS, status_registers
from tests.hmi.helpers import ImageSource, SlaveThread

pytestmark = pytest.mark.skipif(
    shutil.which("mbpoll") is None, reason="mbpoll is not installed (apt-get install -y mbpoll)"
)

VALUE_LINE = re.compile(r"^\[(\d+)\]:\s+(-?\d+)$", re.MULTILINE)


def mbpoll(port: int, *args: str, values: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    cmd = ["mbpoll", "-m", "tcp", "-p", str(port), "-a", "1", "-0", "-1", "-o", "2"]
    cmd += [*args, "127.0.0.1", *values]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=15, check=False)


def read(port: int, table: str, address: int, count: int) -> dict[int, int]:
    result = mbpoll(port, "-t", table, "-r", str(address), "-c", str(count))
    assert result.returncode == 0, result.stderr
    return {int(a): int(v) for a, v in VALUE_LINE.findall(result.stdout)}


def test_mbpoll_reads_coils(slave: SlaveThread) -> None:
    assert read(slave.port, "0", 796, 8) == {
        796: 0,
        797: 0,
        798: 0,
        799: 1,  # %QX99.7
        800: 0,  # %MX0.0
        801: 1,
        802: 0,
        803: 0,
    }


def test_mbpoll_reads_discrete_inputs(slave: SlaveThread) -> None:
    assert read(slave.port, "1", 0, 4) == {0: 0, 1: 0, 2: 1, 3: 0}


def test_mbpoll_reads_input_registers_and_status(slave: SlaveThread, source: ImageSource) -> None:
    assert read(slave.port, "3", 1022, 2) == {1022: 1022, 1023: 1023}
    status = read(slave.port, "3", 1024, STATUS_WORDS)
    assert list(status.values()) == status_registers(source.latest().status)


def test_mbpoll_reads_holding_registers(slave: SlaveThread) -> None:
    assert read(slave.port, "4", 1023, 2) == {1023: 2023, 1024: 5000}


def test_mbpoll_writes(slave: SlaveThread, source: ImageSource) -> None:
    assert mbpoll(slave.port, "-t", "4", "-r", "1030", values=("1234",)).returncode == 0
    assert mbpoll(slave.port, "-t", "4", "-r", "0", values=("7", "8")).returncode == 0
    assert mbpoll(slave.port, "-t", "0", "-r", "800", values=("1", "0", "1")).returncode == 0
    assert mbpoll(slave.port, "-t", "0", "-r", "3", values=("0",)).returncode == 0
    assert source.writes == [
        HmiWrite(parse_address("%MW6"), (1234,)),
        HmiWrite(parse_address("%QW0"), (7, 8)),
        HmiWrite(parse_address("%MX0.0"), (1, 0, 1)),
        HmiWrite(parse_address("%QX0.3"), (0,)),
    ]
    source.publish()
    assert read(slave.port, "4", 1030, 1) == {1030: 1234}


def test_mbpoll_sees_illegal_data_address(slave: SlaveThread) -> None:
    result = mbpoll(slave.port, "-t", "4", "-r", "2559", "-c", "2")  # %MD255's low word, a gap
    assert result.returncode == 1
    assert "Illegal data address" in result.stderr
    result = mbpoll(slave.port, "-t", "4", "-r", "2048", values=("1",))
    assert result.returncode == 1
    assert "Illegal data address" in result.stderr
