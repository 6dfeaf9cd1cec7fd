"""A NaN or an infinity that reaches a guard is said (issue 39 item 4; docs/programs.md, NaN
and infinities): the shipped tank program (programs/tank.yaml) on a real ScanLoop and a
virtual clock. A NaN's bits in the real setpoint `fill_to` (%MD2, as a Modbus register write
of a `finite: false` symbol or a retained value puts them there) used to stop the filling
with no event, diagnostic or fault; now the scan says `not_finite:fill_to:modbus` once, live
`why` names the door beside the value. A device input's NaN is said as a device's."""

from __future__ import annotations

import math
import struct
from pathlib import Path

from softplc.core.datatypes import SymType, raw_of
from softplc.core.image import parse_address, split_registers
from softplc.core.problems import ProgramError
from softplc.core.snapshot import HmiWrite
from softplc.core.why import explain
from softplc.program.io_image import parse_io_image
from softplc.runtime.clock import VirtualClock
from softplc.runtime.config import LoopConfig
from softplc.runtime.loop import ScanLoop

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000


class Tank:
    def __init__(self, program: Path) -> None:
        self.loop = ScanLoop(LoopConfig(program=str(program), start=True, period_ns=10 * MS),
                             None, None, VirtualClock(0))
        self.now = 0
        self.loop.scan_once(0)

    def scan(self, *writes: HmiWrite) -> tuple[str, ...]:
        self.now += 10 * MS
        return tuple(self.loop.runner.step(self.now, (), list(writes)).events)

    def why(self, transition: str) -> str:
        plc = self.loop.runner.plc
        assert plc.net is not None and plc.engine is not None and plc.context is not None
        found = explain(plc.net, plc.engine.state, plc.context, self.now, transition)
        return "; ".join(r.text for r in found.reasons)


def real_write(address: str, value: float) -> HmiWrite:
    at = parse_address(address)
    bits = struct.unpack("<I", struct.pack("<f", value))[0] if math.isnan(value) \
        else raw_of(SymType.REAL, value)
    return HmiWrite(at, tuple(split_registers(bits, at.width)))


def test_a_nan_setpoint_is_said_once_with_its_door_and_why_names_it() -> None:
    tank = Tank(ROOT / "programs" / "tank.yaml")
    said = [e for _ in range(3) for e in tank.scan() if e.startswith("not_finite")]
    assert said == []  # a finite setpoint: nothing
    events = [tank.scan(real_write("%MD2", math.nan))]
    events += [tank.scan() for _ in range(20)]
    said = [e for scan in events for e in scan if e.startswith("not_finite")]
    assert said == ["not_finite:fill_to:modbus"]  # once, not every scan
    plc = tank.loop.runner.plc
    waiting = "start_fill" if plc.marking().get("idle") else "reached"
    text = tank.why(waiting)
    assert "fill_to = NaN (not a number: it came in through a Modbus register write" in text, \
        text
    # A finite value again, then a NaN again: said again.
    tank.scan(real_write("%MD2", 80.0))
    assert not any(e.startswith("not_finite") for e in tank.scan())
    again = tank.scan(real_write("%MD2", math.inf)) + tank.scan()
    assert [e for e in again if e.startswith("not_finite")] == ["not_finite:fill_to:modbus"]


IO = """\
symbols:
  flow: {address: "%ID0", type: real, driver: none}
  lamp: {address: "%QX0.0", type: bool}
"""
PROGRAM = """\
program: flow
io_image: io.yaml
places:
  low: {tokens: 1}
  high: {outputs: [lamp]}
transitions:
  rise: {from: [low], to: [high], when: flow > 10.0}
"""


def test_a_device_input_nan_is_said_as_a_device_input(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "flow.yaml").write_text(PROGRAM, encoding="utf-8")
    plant = Tank(tmp_path / "flow.yaml")
    plant.loop.runner.inputs.id[0] = 0x7FC00000  # the device delivers a NaN
    said = [e for _ in range(5) for e in plant.scan() if e.startswith("not_finite")]
    assert said == ["not_finite:flow:device"]
    assert "flow = NaN (not a number: it came in through a device input)" in plant.why("rise")


def test_the_finite_key_is_checked_at_its_line() -> None:
    good = parse_io_image('symbols:\n  sp: {address: "%MD0", type: real, finite: false}\n'
                          '  ok: {address: "%MD1", type: real}\n', "io.yaml")
    assert (good.symbols["sp"].finite, good.symbols["ok"].finite) == (False, True)
    text = ('symbols:\n  a: {address: "%MD0", type: real, finite: "no"}\n'
            '  b: {address: "%MW0", type: int, finite: true}\n')
    try:
        parse_io_image(text, "io.yaml")
    except ProgramError as exc:
        problems = [str(p) for p in exc.problems]
    else:
        raise AssertionError("accepted")
    assert any(p.startswith("io.yaml:2: symbols.a.finite: finite must be true or false")
               for p in problems), problems
    assert any(p.startswith("io.yaml:3: symbols.b.finite: finite applies to real and lreal")
               for p in problems), problems
