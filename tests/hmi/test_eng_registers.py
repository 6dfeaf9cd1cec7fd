"""Scaled symbols served in engineering units (`scale: {..., modbus: eng}`, issue 30;
docs/modbus.md, scaled symbols): a real program scanned by a real ScanLoop on a virtual clock,
its status board document and published image behind the real slave on 127.0.0.1, read and
written with the real pymodbus client (and Debian's mbpoll); what the HMI reads and writes is
decoded and encoded here with struct, not with softplc's code."""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pymodbus.client import ModbusTcpClient
from pymodbus.pdu import ExceptionResponse

from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.core.snapshot import HmiWrite, Snapshot
from softplc.hmi.eng import EngSource
from softplc.hmi.server import ModbusSlave
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.hmi.helpers import SlaveThread, run_in_thread
from tests.support import eventually

WORDS, MD, ML, ID, IL = 1024, 2048, 4096, 2048, 4096  # register bases, default sizes
IO = """symbols:
  level:    {address: '%IW0', type: int,
             scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%', modbus: eng}}
  level_raw: {address: '%IW1', type: int, scale: {raw: [0, 27648], eng: [0.0, 100.0]}}
  gain:     {address: '%IW2', type: int, scale: {raw: [0, 1], eng: [0, 100000], modbus: eng}}
  temp:     {address: '%ID0', type: real, scale: {raw: [0, 1000], eng: [-50, 150], modbus: eng}}
  energy:   {address: '%IL0', type: lreal, scale: {raw: [0, 1], eng: [0, 3600], modbus: eng}}
  setpoint: {address: '%MW0', type: int, init: 80,
             scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%', clamp: true, modbus: eng}}
  speed:    {address: '%MW1', type: word, scale: {raw: [0, 1000], eng: [0, 50], modbus: eng}}
  offset:   {address: '%MW2', type: int, scale: {raw: [-1000, 1000], eng: [-10, 10], modbus: eng}}
  valve:    {address: '%MW3', type: int, init: 25, scale: {raw: [0, 27648], eng: [0, 100]}}
  flow:     {address: '%MD0', type: real, init: 12.5,
             scale: {raw: [0, 100], eng: [0, 1000], unit: 'l/min', modbus: eng}}
"""
PROGRAM = "program: eng\nio_image: io.yaml\nplaces: {idle: {tokens: 1}}\n"
MS = 1_000_000


def f32(registers: list[int]) -> float:
    return float(struct.unpack(">f", struct.pack(">2H", *registers))[0])


def f64(registers: list[int]) -> float:
    return float(struct.unpack(">d", struct.pack(">4H", *registers))[0])


def regs_f32(value: float) -> list[int]:
    return list(struct.unpack(">2H", struct.pack(">f", value)))


def signed(register: int) -> int:
    return int(struct.unpack(">h", struct.pack(">H", register))[0])


class LivePlc:
    """A real program on a ScanLoop behind the SnapshotSource contract: `scan()` runs one scan
    with the HMI writes journaled since the last one and publishes the image and status; the
    board document is refreshed by `scan()` too, or lags behind it (`board=False`), as the
    runtime's board, refreshed about every 50 ms, can."""

    def __init__(self, program: Path) -> None:
        config = LoopConfig(program=str(program), start=True, period_ns=10 * MS)
        self.loop = ScanLoop(config, None, None, VirtualClock(0))
        self.inputs = self.loop.runner.inputs
        self.writes: list[HmiWrite] = []
        self._lock = threading.Lock()
        self._now = 0
        self.loop.scan_once(0)  # the download and the start
        self._publish(board=True)

    def latest(self) -> Snapshot:
        with self._lock:
            return self._snapshot

    def sink(self, write: HmiWrite) -> None:
        with self._lock:
            self.writes.append(write)

    def board(self) -> dict[str, Any]:
        with self._lock:
            return self._document

    def scan(self, commands: tuple[ProgramCommand, ...] = (), board: bool = True) -> None:
        with self._lock:
            writes, self.writes = self.writes, []
        self._now += 10 * MS
        self.loop.runner.step(self._now, commands, writes)
        self._publish(board)

    def _publish(self, board: bool) -> None:
        plc = self.loop.runner.plc
        snapshot = Snapshot(plc.scan_count, plc.image.copy(), self.loop.status())
        with self._lock:
            self._snapshot = snapshot
            if board:
                self._document = self.loop.document()


@pytest.fixture
def live(tmp_path: Path) -> LivePlc:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "eng.yaml").write_text(PROGRAM, encoding="utf-8")
    plc = LivePlc(tmp_path / "eng.yaml")
    plc.inputs.iw[0], plc.inputs.iw[1], plc.inputs.iw[2] = 13824, 13824, 1
    plc.inputs.id[0] = struct.unpack("<I", struct.pack("<f", 437.5))[0]  # 37.5 degrees
    plc.inputs.il[0] = struct.unpack("<Q", struct.pack("<d", 0.25))[0]  # 900.0
    plc.scan()
    return plc


@pytest.fixture
def slave(live: LivePlc) -> Iterator[SlaveThread]:
    modbus = ModbusSlave(live, live.sink, sizes=live.loop.runner.plc.image.sizes, port=0,
                         presentation=EngSource(live.board, live))
    with run_in_thread(modbus) as handle:
        yield handle


@pytest.fixture
def client(slave: SlaveThread) -> Iterator[ModbusTcpClient]:
    c = ModbusTcpClient("127.0.0.1", port=slave.port, timeout=3, retries=0)
    assert c.connect()
    yield c
    c.close()


def holding(client: ModbusTcpClient, address: int, count: int) -> list[int]:
    reply = client.read_holding_registers(address, count=count, device_id=1)
    assert not reply.isError(), reply
    return list(reply.registers)


def inputs(client: ModbusTcpClient, address: int, count: int) -> list[int]:
    reply = client.read_input_registers(address, count=count, device_id=1)
    assert not reply.isError(), reply
    return list(reply.registers)


def exception_code(reply: object) -> int:
    assert isinstance(reply, ExceptionResponse), reply
    return int(reply.exception_code)


def test_reads_carry_engineering_values_in_the_symbols_types(client: ModbusTcpClient) -> None:
    # level 13824 of 0..27648 is 50 %; level_raw keeps the default: its raw count
    assert inputs(client, 0, 3) == [50, 13824, 32767]  # gain: 100000 held to int's range
    assert f32(inputs(client, ID, 2)) == 37.5  # temp: a real register, the float
    assert f64(inputs(client, IL, 4)) == 900.0  # energy: an lreal, the double
    # setpoint and flow start at their init: (80 %, 12.5 l/min); valve is raw (25 % = 6912)
    assert holding(client, WORDS, 4) == [80, 0, 0, 6912]
    assert f32(holding(client, MD, 2)) == 12.5


def test_integer_registers_round_half_to_even_and_hold_to_the_type(
        live: LivePlc, client: ModbusTcpClient) -> None:
    image = live.loop.runner.plc.image
    image.mw[1] = 65535  # speed: 3276.75 -> 3277, fits a word
    image.mw[2] = (-250) & 0xFFFF  # offset: -2.5 -> -2 (ties to even)
    live.inputs.iw[2] = (-1) & 0xFFFF  # gain: -100000 -> -32768
    live.scan()
    assert holding(client, WORDS + 1, 2) == [3277, (-2) & 0xFFFF]
    image.mw[2] = 350  # 3.5 -> 4
    live.scan()
    assert signed(holding(client, WORDS + 2, 1)[0]) == 4
    assert signed(inputs(client, 2, 1)[0]) == -32768


def test_writes_are_converted_back_to_raw_as_the_api_converts_them(
        live: LivePlc, client: ModbusTcpClient) -> None:
    image = live.loop.runner.plc.image
    assert not client.write_register(WORDS, 55, device_id=1).isError()  # setpoint 55 %
    assert not client.write_registers(WORDS + 1, [20, (-3) & 0xFFFF, 13824],
                                      device_id=1).isError()  # speed, offset, valve (raw)
    assert not client.write_registers(MD, regs_f32(250.0), device_id=1).isError()  # flow
    assert live.writes == [HmiWrite(live.loop.runner.plc.net.io.symbols["setpoint"].address,
                                    (15206,)),  # 55 % of 27648 = 15206.4, to the nearest
                           HmiWrite(image_address("%MW1"), (400, (-300) & 0xFFFF, 13824)),
                           HmiWrite(image_address("%MD0"), tuple(split32(25.0)))]
    live.scan()
    assert (image.mw[0], image.mw[1], image.mw[2], image.mw[3]) == (15206, 400, 65236, 13824)
    assert holding(client, WORDS, 4) == [55, 20, (-3) & 0xFFFF, 13824]  # read back
    assert f32(holding(client, MD, 2)) == 250.0
    # clamp: true limits a write to the span, as the program's and the API's writes
    assert not client.write_register(WORDS, 150, device_id=1).isError()
    live.scan()
    assert (image.mw[0], holding(client, WORDS, 1)) == (27648, [100])


def test_a_value_the_symbol_cannot_take_is_exception_03_and_nothing_is_journaled(
        live: LivePlc, client: ModbusTcpClient) -> None:
    # speed 0..50 on raw 0..1000 without clamp: 3300 is raw 66000, beyond a word
    assert exception_code(client.write_register(WORDS + 1, 3300, device_id=1)) == 3
    # a NaN for flow, and a request of which one value is refused: refused whole
    assert exception_code(client.write_registers(MD, regs_f32(float("nan")),
                                                 device_id=1)) == 3
    assert exception_code(client.write_registers(WORDS, [50, 3300], device_id=1)) == 3
    assert live.writes == []


@pytest.mark.parametrize("served_before", [True, False])
def test_while_the_board_does_not_describe_the_running_program_register_writes_are_06(
        live: LivePlc, client: ModbusTcpClient, tmp_path: Path, served_before: bool) -> None:
    """A snapshot of a program the board does not describe yet (the runtime publishes the
    board first; a board that lags is the case this guards): reads are served with the last
    table read, and a register write, which the previous program's scale (or none, if the
    slave has read no table yet) would convert wrongly, is refused with 06 (busy: retry)."""
    if served_before:
        assert holding(client, WORDS, 1) == [80]  # the slave has read v1's table
    (tmp_path / "v2").mkdir()
    (tmp_path / "v2" / "io.yaml").write_text(
        IO.replace("eng: [0.0, 100.0], unit: '%', clamp: true", "eng: [0.0, 200.0], clamp: true"),
        encoding="utf-8")
    (tmp_path / "v2" / "eng.yaml").write_text(PROGRAM, encoding="utf-8")
    v2 = compile_file(tmp_path / "v2" / "eng.yaml")
    live.scan((ProgramCommand(Command.DOWNLOAD, v2, online=True),), board=False)
    assert live.latest().status.program_hash == v2.program_hash != live.board()["program_hash"]
    assert exception_code(client.write_register(WORDS, 55, device_id=1)) == 6
    assert exception_code(client.write_register(WORDS + 3, 100, device_id=1)) == 6  # valve
    assert client.write_coil(800, True, device_id=1).isError() is False  # bits are not scaled
    assert live.writes == [HmiWrite(image_address("%MX0.0"), (1,))]
    live.writes.clear()
    # The new scale makes setpoint another variable: the download put its init there (80 of
    # 0..200, raw 11059); a lagging board's last table would show that raw value as 40
    if served_before:
        assert holding(client, WORDS, 1) == [40]
    live.scan()  # the board follows (the slave reads it again within RECHECK_S)
    eventually(lambda: holding(client, WORDS, 1) == [80], what="v2's presentation")
    assert not client.write_register(WORDS, 55, device_id=1).isError()
    assert live.writes == [HmiWrite(image_address("%MW0"), (7603,))]  # 55 of 200 = 7603.2


def image_address(text: str) -> Any:
    from softplc.core.image import parse_address

    return parse_address(text)


def split32(value: float) -> list[int]:
    return list(struct.unpack(">2H", struct.pack(">f", value)))


VALUE_LINE = re.compile(r"^\[(\d+)\]:\s+(-?[\d.]+)$", re.MULTILINE)


@pytest.mark.skipif(shutil.which("mbpoll") is None, reason="Debian's mbpoll is not installed")
def test_mbpoll_reads_and_writes_engineering_values(live: LivePlc, slave: SlaveThread) -> None:
    def mbpoll(*args: str) -> str:
        done = subprocess.run(["mbpoll", "-m", "tcp", "-p", str(slave.port), "-a", "1", "-0",
                               "-1", "-o", "2", *args], capture_output=True, text=True,
                              timeout=15, check=False)
        assert done.returncode == 0, done.stderr
        return done.stdout

    assert VALUE_LINE.findall(mbpoll("-t", "3", "-r", "0", "-c", "2", "127.0.0.1")) == [
        ("0", "50"), ("1", "13824")]
    assert VALUE_LINE.findall(mbpoll("-t", "4:float", "-B", "-r", str(MD), "127.0.0.1")) == [
        (str(MD), "12.5")]
    assert "Written 1 references" in mbpoll("-t", "4", "-r", str(WORDS), "127.0.0.1", "60")
    assert "Written 1 references" in mbpoll("-t", "4:float", "-B", "-r", str(MD), "127.0.0.1",
                                            "99.5")
    live.scan()
    image = live.loop.runner.plc.image
    assert image.mw[0] == 16589  # 60 % of 27648 = 16588.8
    stored = struct.unpack("<f", struct.pack("<I", int(image.md[0])))[0]  # 99.5 l/min: 9.95
    assert stored == struct.unpack("<f", struct.pack("<f", 9.95))[0]  # as a single
    assert VALUE_LINE.findall(mbpoll("-t", "4", "-r", str(WORDS), "127.0.0.1")) == [
        (str(WORDS), "60")]
