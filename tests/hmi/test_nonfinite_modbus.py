"""NaN and infinities at the Modbus door (issue 39 item 4; docs/programs.md, NaN and
infinities): the shipped tank program (programs/tank.yaml) scanned by a real ScanLoop on a
virtual clock, behind the real slave on 127.0.0.1 with the runtime's EngSource, written with
the pymodbus client. A NaN's or an infinity's bits written into the real setpoint `fill_to`
(%MD2) are refused with exception 03 and never reach the image; a finite value goes through;
`finite: false` on the symbol lets them in. The bits are made here with struct."""

from __future__ import annotations

import math
import shutil
import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from softplc.core.datatypes import SymType, value_of
from softplc.hmi.eng import EngSource
from softplc.hmi.server import ModbusSlave
from tests.hmi.helpers import run_in_thread
from tests.hmi.test_eng_registers import MD, LivePlc, regs_f32

ROOT = Path(__file__).resolve().parents[2]
FILL_TO = MD + 2 * 2  # %MD2: two holding registers per double word


def tank(tmp_path: Path, finite: bool) -> LivePlc:
    (tmp_path / "programs").mkdir()
    (tmp_path / "io_images").mkdir()
    shutil.copy(ROOT / "programs" / "tank.yaml", tmp_path / "programs" / "tank.yaml")
    io = (ROOT / "io_images" / "tank.yaml").read_text(encoding="utf-8")
    if not finite:
        io = io.replace('fill_to:      {address: "%MD2", type: real,',
                        'fill_to:      {address: "%MD2", type: real, finite: false,')
        assert "finite: false" in io
    (tmp_path / "io_images" / "tank.yaml").write_text(io, encoding="utf-8")
    return LivePlc(tmp_path / "programs" / "tank.yaml")


def fill_to(live: LivePlc) -> float:
    plc = live.loop.runner.plc
    return float(value_of(SymType.REAL, int(plc.image.md[2])))


@pytest.fixture
def served(tmp_path: Path, request: pytest.FixtureRequest
           ) -> Iterator[tuple[LivePlc, ModbusTcpClient]]:
    live = tank(tmp_path, request.param)
    live.scan()
    modbus = ModbusSlave(live, live.sink, sizes=live.loop.runner.plc.image.sizes, port=0,
                         presentation=EngSource(live.board, live))
    with run_in_thread(modbus) as handle:
        c = ModbusTcpClient("127.0.0.1", port=handle.port, timeout=3, retries=0)
        assert c.connect()
        try:
            yield live, c
        finally:
            c.close()


@pytest.mark.parametrize("served", [True], indirect=True)
def test_nan_and_infinities_are_refused_with_03(served: tuple[LivePlc, ModbusTcpClient]
                                                ) -> None:
    live, c = served
    assert fill_to(live) == 80.0  # its init:
    for bad in (math.nan, math.inf, -math.inf):
        reply = c.write_registers(FILL_TO, regs_f32(bad))
        assert reply.isError() and reply.exception_code == 3, (bad, reply)
    nan_bits = list(struct.unpack(">2H", struct.pack(">I", 0x7FC00001)))  # a NaN with payload
    assert c.write_registers(FILL_TO, nan_bits).exception_code == 3
    assert live.writes == []  # nothing of it was queued for the scan
    live.scan()
    assert fill_to(live) == 80.0
    assert not c.write_registers(FILL_TO, regs_f32(75.5)).isError()  # a number goes through
    live.scan()
    assert fill_to(live) == 75.5


@pytest.mark.parametrize("served", [False], indirect=True)
def test_finite_false_lets_a_modbus_write_store_one(served: tuple[LivePlc, ModbusTcpClient]
                                                    ) -> None:
    live, c = served
    assert not c.write_registers(FILL_TO, regs_f32(math.nan)).isError()
    live.scan()
    assert math.isnan(fill_to(live))
