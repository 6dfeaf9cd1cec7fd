"""Live `why` shows what the program reads (issue 39, item 1): on the shipped tank program,
run in-process on a virtual clock, the explanation built from the status board as
GET /api/v1/why/{transition} builds it (api/debug.py) shows a `real` as a real and a scaled
symbol in engineering units with its unit, forces included; never the image's raw bits."""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any

from softplc.api.debug import explain_board
from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.core.why import format_why
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000


def f32(value: float) -> int:
    return int(struct.unpack("<I", struct.pack("<f", value))[0])


class Cycles:
    """The loop's stop flag: forces once the tank fills, the board kept at the last cycle."""

    def __init__(self, loop: ScanLoop, end: int) -> None:
        self.loop, self.end, self.cycle = loop, end, 0
        self.doc: dict[str, Any] = {}

    def is_set(self) -> bool:
        self.cycle += 1
        if self.cycle == self.end // 2:
            self.loop.pending += [
                ProgramCommand(Command.FORCE, symbol="min_temp", value=f32(12.5)),
                ProgramCommand(Command.FORCE, symbol="temperature", value=15)]  # raw: 1.5 °C
        if self.cycle == self.end:
            self.doc = self.loop.document()
        return self.cycle > self.end

    def set(self) -> None:
        self.cycle = self.end

    def wait(self, timeout: float | None = None) -> bool:
        return self.is_set()


def test_live_why_on_the_tank_shows_reals_and_engineering_units() -> None:
    config = LoopConfig(program=str(ROOT / "programs/tank.yaml"), start=True,
                        period_ns=10 * MS, plant="tank")
    loop = ScanLoop(config, None, None, VirtualClock(0))  # type: ignore[arg-type]
    cycles = Cycles(loop, 50)
    loop.run(cycles)  # type: ignore[arg-type]
    doc, net = cycles.doc, loop.runner.plc.net
    assert net is not None and doc["marking"] == {"filling": 1}, doc["marking"]
    level = doc["symbols"]["level"]["raw"] * 100 / 27648  # 0..27648 = 0..100 %: 3 decimals
    assert 0 < level < 80

    reached = format_why(explain_board(net, doc, "reached").as_dict())
    assert reached == [
        "reached: blocked",
        "  - guard level >= fill_to or high_switch is false with fill_to = 80.0, "
        f"high_switch = 0, level = {level:.3f} %"]

    start_fill = explain_board(net, doc, "start_fill").as_dict()
    assert [r["text"] for r in start_fill["reasons"][:4]] == [
        "idle: 0 of 1",
        "guard level < fill_to and temperature > min_temp and not high_switch: temperature > "
        "min_temp is false with min_temp = 12.5 (forced), temperature = 1.5 °C (forced)",
        "min_temp is forced to 12.5 (read by its guard)",
        "temperature is forced to 1.5 °C (read by its guard)"]
