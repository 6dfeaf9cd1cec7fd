"""A NaN or an infinity arriving from a device input is said on arrival (issue 39 item 4,
core/nonfinite.py `arrived`): the event `not_finite:SYMBOL:device:DRIVER` once when a real or
lreal input's latched value stops being finite, again only after it was finite in between,
whether or not a guard reads it (before: only when a guard or an action read it, so a NaN on
an input the current marking does not look at went unsaid). A scan loop whose remote I/O is
a real pymodbus server on 127.0.0.1, stepped scan by scan on the real clock; every wait is
bounded in scans."""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from softplc.core.datatypes import SymType, raw_of
from softplc.core.image import ImageSizes, ProcessImage, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.nonfinite import arrived
from softplc.core.symbols import Direction, Symbol
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.support import SimModbusServer, free_port

FC_HR, FC_IR = 3, 4
MAX_SCANS = 2000  # about 5 s at 2 ms a scan: far beyond any wait here

IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: 0.2,
         reconnect_min_s: 0.05, reconnect_max_s: 0.1}}
symbols:
  flow:   {{address: "%ID0", type: real, channel: "ir:10"}}
  energy: {{address: "%IL0", type: lreal, channel: "hr:20"}}
  lamp:   {{address: "%QX0.0", channel: "coil:0", safe: false}}
"""
# No guard reads flow or energy while `on` holds the token: `rise` needs `never`.
PROGRAM = """\
program: quiet
io_image: io.yaml
places:
  on: {tokens: 1, outputs: [lamp]}
  never: {}
transitions:
  rise: {from: [never], to: [on], when: flow > 10.0 or energy > 1.0}
"""


def real_words(value: float) -> list[int]:
    bits = struct.unpack(">I", struct.pack(">f", value))[0]
    return [bits >> 16, bits & 0xFFFF]  # big word order, the driver's default


def lreal_words(value: float) -> list[int]:
    bits = struct.unpack(">Q", struct.pack(">d", value))[0]
    return [(bits >> s) & 0xFFFF for s in (48, 32, 16, 0)]


@pytest.fixture
def server() -> Iterator[SimModbusServer]:
    srv = SimModbusServer(free_port())
    srv.start()
    yield srv
    srv.dispose()


def test_a_device_nan_is_said_on_arrival_once(server: SimModbusServer, tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO.format(port=server.port), encoding="utf-8")
    (tmp_path / "quiet.yaml").write_text(PROGRAM, encoding="utf-8")
    loop = ScanLoop(LoopConfig(program=str(tmp_path / "quiet.yaml"), start=True), None, None)
    said: list[str] = []

    def until(cond: Callable[[], bool]) -> bool:
        for _ in range(MAX_SCANS):
            loop.scan_once(time.monotonic_ns())
            said[:] = [e["name"] for e in loop.events if e["name"].startswith("not_finite")]
            if cond():
                return True
            time.sleep(0.002)
        return False

    def flow() -> float:
        return float(loop.runner.plc.image.id[:1].view("<f4")[0])

    try:
        server.set(FC_IR, 10, real_words(1.5))
        server.set(FC_HR, 20, lreal_words(2.5))
        assert until(lambda: flow() == 1.5)
        assert loop.runner.plc.state is PlcState.RUNNING and said == []
        server.set(FC_IR, 10, real_words(float("nan")))
        assert until(lambda: math.isnan(flow()))  # the NaN latched
        for _ in range(50):  # more scans with the NaN: said once, not every scan
            until(lambda: True)
        assert said == ["not_finite:flow:device:rio"]
        server.set(FC_IR, 10, real_words(float("inf")))  # NaN -> inf: still not finite
        server.set(FC_HR, 20, lreal_words(float("-inf")))
        assert until(lambda: said[1:] == ["not_finite:energy:device:rio"])
        server.set(FC_IR, 10, real_words(3.0))
        assert until(lambda: flow() == 3.0)
        server.set(FC_IR, 10, real_words(float("-inf")))  # finite in between: said again
        assert until(lambda: len(said) == 3)
        for _ in range(20):
            until(lambda: True)
        assert said == ["not_finite:flow:device:rio", "not_finite:energy:device:rio",
                        "not_finite:flow:device:rio"]
    finally:
        loop.shutdown()


@pytest.mark.parametrize("count", [3, 40])  # one test each, and numpy's for many in an area
def test_arrived_says_exactly_the_inputs_that_stopped_being_finite(count: int) -> None:
    symbols = {f"r{i}": Symbol(f"r{i}", parse_address(f"%ID{i}"), SymType.REAL, Direction.IN,
                               driver="rio") for i in range(count)}
    symbols["d"] = Symbol("d", parse_address(f"%ID{count}"), SymType.DINT, Direction.IN)
    symbols["m"] = Symbol("m", parse_address("%MD0"), SymType.REAL, Direction.MEMORY)
    image, prev = ProcessImage(ImageSizes()), ProcessImage(ImageSizes())
    nan, inf = 0x7FC00000, 0x7F800000  # a real's bits
    assert arrived(image, prev, symbols) == ()
    image.id[count] = 0x7FC00000  # a dint with a NaN's bits is a number
    image.md[0] = nan  # not an input: said when read (core/context.py)
    image.id[1], image.id[count - 1] = nan, inf
    prev.id[count - 1] = nan  # not finite the scan before: said then
    assert arrived(image, prev, symbols) == ("not_finite:r1:device:rio",)
    prev.id[count - 1] = raw_of(SymType.REAL, 2.5)
    assert arrived(image, prev, symbols) == ("not_finite:r1:device:rio",
                                             f"not_finite:r{count - 1}:device:rio")
