"""32- and 64-bit symbols on Modbus remote I/O (issue 30): the register plan in-process, then
the driver against a real pymodbus server on 127.0.0.1, in both word orders. The server side
encodes and decodes with struct, never with the code under test. Every wait is bounded."""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from types import MappingProxyType
from typing import Any

import pytest

from softplc.core.datatypes import raw_of, value_of
from softplc.core.image import ProcessImage, parse_address
from softplc.core.symbols import DIRECTION_OF_AREA, DriverSpec, Symbol, SymType
from softplc.devices.driver import DriverConfigError
from softplc.devices.modbus_io import Block, ModbusIoDriver, ModbusParams, Table, plan_channels
from tests.support import SimModbusServer, free_port, wait_until

FC_HR, FC_IR, FC_WRITE_HR = 3, 4, 16
DRIVER = "rio"


def sym(name: str, address: str, channel: str, kind: SymType) -> Symbol:
    addr = parse_address(address)
    return Symbol(name, addr, kind, DIRECTION_OF_AREA[addr.area], driver=DRIVER, channel=channel)


def spec(port: int, **params: Any) -> DriverSpec:
    base: dict[str, Any] = {"host": "127.0.0.1", "port": port, "timeout_s": 0.2,
                            "reconnect_min_s": 0.05, "reconnect_max_s": 0.2}
    base.update(params)
    return DriverSpec(DRIVER, "modbus", MappingProxyType(base))


SYMBOLS = [
    sym("flow", "%ID0", "ir:10", SymType.REAL),
    sym("count", "%ID1", "ir:12", SymType.DINT),
    sym("energy", "%IL0", "hr:20", SymType.LREAL),
    sym("level", "%IW0", "ir:0", SymType.INT),
    sym("setp", "%QD0", "hr:0", SymType.REAL),
    sym("total", "%QD1", "hr:2", SymType.DINT),
    sym("big", "%QL0", "hr:4", SymType.LREAL),
]


# -- the plan -----------------------------------------------------------------------------------

def test_wide_values_take_consecutive_registers_in_one_request_each() -> None:
    plan = plan_channels(SYMBOLS)
    assert plan.reads == (Block(Table.HR, 20, (0,), 4), Block(Table.IR, 0, (0,)),
                          Block(Table.IR, 10, (0, 1), 2))
    assert [b.count for b in plan.reads] == [4, 1, 4]
    assert plan.writes == (Block(Table.HR, 0, (0, 1), 2), Block(Table.HR, 4, (0,), 4))


def test_a_request_never_splits_a_value() -> None:
    many = [sym(f"v{i}", f"%ID{i}", f"ir:{2 * i}", SymType.DINT) for i in range(70)]
    blocks = plan_channels(many).reads
    assert [b.count for b in blocks] == [124, 16]  # 125 registers at most: 62 values, then 8


@pytest.mark.parametrize(("symbols", "message"), [
    ([sym("a", "%ID0", "ir:0", SymType.DINT), sym("b", "%IW0", "ir:1", SymType.WORD)],
     "channel 'ir:1' is already used by symbol 'a'"),
    ([sym("a", "%IW0", "ir:1", SymType.WORD), sym("b", "%ID0", "ir:0", SymType.DINT)],
     "channel 'ir:0' (its register ir:1) is already used by symbol 'a'"),
    ([sym("a", "%IL0", "hr:65533", SymType.LREAL)], "needs registers 65533..65536"),
    ([sym("a", "%QD0", "ir:0", SymType.DINT)], "a 32-bit value (2 registers) output"),
])
def test_overlapping_and_misplaced_wide_channels_are_refused(symbols: list[Symbol],
                                                             message: str) -> None:
    with pytest.raises(ValueError, match="modbus channels") as err:
        plan_channels(symbols)
    assert message in str(err.value)


def test_word_order_must_be_big_or_little() -> None:
    assert ModbusParams.from_spec(spec(502)).word_order == "big"
    with pytest.raises(DriverConfigError, match="word_order 'middle': expected big"):
        ModbusParams.from_spec(spec(502, word_order="middle"))


# -- against a real server ----------------------------------------------------------------------

def registers(fmt: str, value: float, little: bool) -> list[int]:
    """What a device holds: the value's big-endian bytes cut into registers, high word first
    unless `little`."""
    data = struct.pack(">" + fmt, value)
    regs = [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data), 2)]
    return regs[::-1] if little else regs


def decode(fmt: str, regs: list[int], little: bool) -> float:
    ordered = regs[::-1] if little else regs
    value: float = struct.unpack(">" + fmt, b"".join(r.to_bytes(2, "big") for r in ordered))[0]
    return value


@pytest.fixture
def server() -> Iterator[SimModbusServer]:
    srv = SimModbusServer(free_port())
    srv.start()
    yield srv
    srv.dispose()


@pytest.fixture
def open_driver() -> Iterator[Callable[[DriverSpec], ModbusIoDriver]]:
    made: list[ModbusIoDriver] = []

    def make(driver_spec: DriverSpec) -> ModbusIoDriver:
        drv = ModbusIoDriver(driver_spec, SYMBOLS)
        made.append(drv)
        drv.open()
        return drv

    yield make
    for drv in made:
        drv.close()


@pytest.mark.parametrize("order", ["big", "little"])
def test_reals_dints_and_lreals_flow_in_and_out_in_the_word_order(
        server: SimModbusServer, open_driver: Callable[[DriverSpec], ModbusIoDriver],
        order: str) -> None:
    little = order == "little"
    server.set(FC_IR, 10, registers("f", 12.5, little) + registers("i", -123456, little))
    server.set(FC_HR, 20, registers("d", -1.0e-300, little))
    server.set(FC_IR, 0, [65535])
    driver = open_driver(spec(server.port, word_order=order))
    image = ProcessImage()
    image.qd[0] = raw_of(SymType.REAL, 3.25)
    image.qd[1] = raw_of(SymType.DINT, -7)
    image.ql[0] = raw_of(SymType.LREAL, 6.02e23)
    now = [0]

    def cycle() -> bool:
        now[0] += 10_000_000
        driver.read_inputs(image, now[0])
        driver.write_outputs(image, now[0])
        return bool(image.id[0]) and server.get(FC_HR, 4, 4) != [0, 0, 0, 0]

    assert wait_until(cycle, 3.0, step_s=0.005)
    assert value_of(SymType.REAL, int(image.id[0])) == 12.5
    assert value_of(SymType.DINT, int(image.id[1])) == -123456
    assert value_of(SymType.LREAL, int(image.il[0])) == -1.0e-300
    assert value_of(SymType.INT, int(image.iw[0])) == -1
    out = server.get(FC_HR, 0, 8)
    assert decode("f", out[0:2], little) == 3.25
    assert decode("i", out[2:4], little) == -7
    assert decode("d", out[4:8], little) == 6.02e23
    server.take_requests()
    assert wait_until(lambda: (cycle(), len(server.requests) >= 6)[1], 2.0, step_s=0.005)
    requests = set(server.take_requests())
    # One request per block: each value whole in one FC16 write or FC3/FC4 read.
    assert {(FC_WRITE_HR, 0, 4), (FC_WRITE_HR, 4, 4), (FC_IR, 10, 4), (FC_HR, 20, 4)} <= requests
