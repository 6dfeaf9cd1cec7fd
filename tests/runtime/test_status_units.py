"""Issue 39, item 1 in `softplc status`: a forced value is written as core/present.py writes
it, a scaled one at its scale's resolution with its unit (`47.002 %`, not
47.00159143518518), a real as a real. On programs/tank.yaml run in-process on a virtual
clock; the text is format_status over the status document GET /api/v1/status serves."""

from __future__ import annotations

import re

from softplc.api.clicmds import format_status
from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.debug.test_why_live_values import ROOT, Cycles, f32

MS = 1_000_000


class Forced(Cycles):
    def is_set(self) -> bool:
        if self.cycle + 1 == self.end // 2:
            self.loop.pending += [
                ProgramCommand(Command.FORCE, symbol="level", value=12995),  # 47.0016 %
                ProgramCommand(Command.FORCE, symbol="min_temp", value=f32(2.5)),
                ProgramCommand(Command.FORCE, symbol="temperature", value=65521)]  # -15: -1.5 °C
            self.cycle += 1
            return False
        return super().is_set()


def test_status_text_shows_forced_values_with_units_at_their_resolution() -> None:
    config = LoopConfig(program=str(ROOT / "programs/tank.yaml"), start=True,
                        period_ns=10 * MS, plant="tank")
    loop = ScanLoop(config, None, None, VirtualClock(0))  # type: ignore[arg-type]
    cycles = Forced(loop, 20)
    loop.run(cycles)  # type: ignore[arg-type]
    text = format_status(cycles.doc)
    forced = [re.sub(r"\s+", " ", line.strip()) for line in text.splitlines()
              if line.endswith("FORCED")]
    assert forced == ["level 47.002 % FORCED", "min_temp 2.5 FORCED",
                      "temperature -1.5 °C FORCED"], text
