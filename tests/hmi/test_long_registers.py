"""32- and 64-bit areas over Modbus (issue 30): %MD at holding register 2048 and %ML at 4096
(OpenPLC's map), %QD/%QL after them, %ID/%IL in the input registers; high word first. Read
and written with the real pymodbus client against the real slave on 127.0.0.1, decoded with
struct, not with softplc's code."""

from __future__ import annotations

import struct
from collections.abc import Iterator

import pytest
from pymodbus.client import ModbusTcpClient

from softplc.core.image import ImageSizes
from softplc.hmi.server import ModbusSlave
from tests.hmi.helpers import ImageSource, SlaveThread, run_in_thread


def _bits32(fmt: str, value: float) -> int:
    return int(struct.unpack(">I", struct.pack(fmt, value))[0])


def _bits64(value: float) -> int:
    return int(struct.unpack(">Q", struct.pack(">d", value))[0])


def _decode(fmt: str, registers: list[int]) -> float:
    return float(struct.unpack(fmt, struct.pack(f">{len(registers)}H", *registers))[0])


@pytest.fixture
def long_source() -> ImageSource:
    src = ImageSource(ImageSizes())
    img = src.image
    img.md[0] = _bits32(">f", 12.5)  # a real
    img.md[1] = _bits32(">i", -5)  # a dint
    img.ml[0] = _bits64(-1234.5678)  # an lreal
    img.id[2] = _bits32(">f", -40.25)
    img.il[1] = _bits64(1e100)
    img.qd[0] = _bits32(">I", 4_000_000_000)  # a udint
    img.ql[255] = _bits64(0.1)
    src.publish()
    return src


@pytest.fixture
def long_slave(long_source: ImageSource) -> Iterator[SlaveThread]:
    with run_in_thread(ModbusSlave(long_source, long_source.sink, sizes=long_source.image.sizes,
                                   port=0)) as handle:
        yield handle


@pytest.fixture
def client(long_slave: SlaveThread) -> Iterator[ModbusTcpClient]:
    c = ModbusTcpClient("127.0.0.1", port=long_slave.port, timeout=3, retries=0)
    assert c.connect()
    yield c
    c.close()


def test_values_show_at_their_registers(client: ModbusTcpClient) -> None:
    hr = client.read_holding_registers(2048, count=4).registers
    assert _decode(">f", hr[0:2]) == 12.5
    assert _decode(">i", hr[2:4]) == -5
    assert _decode(">d", client.read_holding_registers(4096, count=4).registers) == -1234.5678
    assert _decode(">I", client.read_holding_registers(8192, count=2).registers) == 4_000_000_000
    ql255 = 10 * 1024 + 4 * 255
    assert _decode(">d", client.read_holding_registers(ql255, count=4).registers) == 0.1
    assert _decode(">f", client.read_input_registers(2048 + 4, count=2).registers) == -40.25
    assert _decode(">d", client.read_input_registers(4096 + 4, count=4).registers) == 1e100
    # A read may start inside a value: the low word of %MD0, then %MD1.
    assert client.read_holding_registers(2049, count=3).registers == hr[1:4]


def test_a_write_of_both_registers_applies_at_the_scan_boundary(
        client: ModbusTcpClient, long_source: ImageSource) -> None:
    registers = list(struct.unpack(">2H", struct.pack(">f", -3.25)))
    assert not client.write_registers(2048 + 6, registers).isError()  # %MD3
    long_registers = list(struct.unpack(">4H", struct.pack(">d", 2.0 ** 0.5)))
    assert not client.write_registers(4096 + 8, long_registers).isError()  # %ML2
    # Journaled, not applied: the image changes only at the next scan, all at once.
    assert long_source.image.md[3] == 0
    long_source.publish()
    assert struct.unpack(">f", struct.pack(">I", int(long_source.image.md[3])))[0] == -3.25
    assert struct.unpack(">d", struct.pack(">Q", int(long_source.image.ml[2])))[0] == 2.0 ** 0.5
    hr = client.read_holding_registers(2048 + 6, count=2).registers
    assert _decode(">f", hr) == -3.25


@pytest.mark.parametrize(("address", "count"), [(2048, 1), (2049, 2), (4096 + 1, 4), (2047, 2)])
def test_half_a_value_is_refused_whole(client: ModbusTcpClient, long_source: ImageSource,
                                       address: int, count: int) -> None:
    reply = client.write_registers(address, [1] * count)
    assert reply.isError() and reply.exception_code == 2
    assert long_source.writes == []


def test_the_gaps_between_areas_are_02(client: ModbusTcpClient) -> None:
    for table_read, address in ((client.read_holding_registers, 2048 + 512),
                                (client.read_input_registers, 1024 + 20)):
        reply = table_read(address, count=1)
        assert reply.isError() and reply.exception_code == 2
