"""While paused, every view runs on the net's clock (issue 39, item 2): the status board's
countdowns (a firing's time left, a delay's time left) stand still however long the pause
lasts, so live `why` and status agree with what the next step does. The drilling cell on a
virtual clock pauses when `drill` fires (busy 2 s); 3 s pass paused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000
PAUSED_CYCLES = 300  # 3 s of the 10 ms period


class PauseWatch:
    """The loop's stop flag: sets the breakpoint, then keeps the board at the pause and
    PAUSED_CYCLES later."""

    def __init__(self, loop: ScanLoop) -> None:
        self.loop, self.cycle, self.paused_at = loop, 0, 0
        self.docs: list[dict[str, Any]] = []

    def is_set(self) -> bool:
        self.cycle += 1
        if self.cycle == 1:
            self.loop.pending.append(ProgramCommand(Command.BREAK, symbol="fire:drill"))
        paused = self.loop.runner.plc.debug.pause is not None
        if paused and not self.paused_at:
            self.paused_at = self.cycle
            self.docs.append(self.loop.document())
        if self.paused_at and self.cycle == self.paused_at + PAUSED_CYCLES:
            self.docs.append(self.loop.document())
            self.loop.pending.append(ProgramCommand(Command.STEP))
        if self.paused_at and self.cycle == self.paused_at + PAUSED_CYCLES + 20:
            self.docs.append(self.loop.document())  # paused again after the one scan
            return True
        return self.cycle > 5000

    def set(self) -> None:
        self.cycle = 5000

    def wait(self, timeout: float | None = None) -> bool:
        return self.is_set()


def test_a_firings_time_left_stands_still_while_paused() -> None:
    config = LoopConfig(program=str(ROOT / "programs/drilling.yaml"), start=True,
                        period_ns=10 * MS, plant="drilling")
    loop = ScanLoop(config, None, None, VirtualClock(0))  # type: ignore[arg-type]
    watch = PauseWatch(loop)
    loop.run(watch)  # type: ignore[arg-type]
    assert len(watch.docs) == 3, "the drill never fired, or the pause never lasted"
    at_pause, later, stepped = (doc["net_live"]["busy"]["drill"]["remaining_ms"]
                                for doc in watch.docs)
    assert at_pause > 1500  # the firing has just begun: about 2 s left
    assert later == at_pause, f"{later} ms left after 3 s paused, {at_pause} at the pause"
    assert watch.docs[2]["paused"] is not None
    assert stepped == at_pause - 10, "a step is one period of the net's time, not 3 s"
