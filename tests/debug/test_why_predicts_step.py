"""Issue 39, item 2, as a property: on random nets with enabling delays and timed firings,
paused at a random scan, live `why` (the explanation GET /api/v1/why builds from the status
board, api/debug.explain_board) predicts exactly the transitions the next `step` fires, and
the status board's countdowns exactly the timed firings it ends, at each of the following
pauses. The PLC is a real ScanLoop on a virtual clock
(10 ms period) whose wall clock runs on while it is paused: a view on the wall clock would
count delays and firings down during the pause and predict firings that do not happen.

Fast by default (a few examples); SOFTPLC_FUZZ_SCALE=N runs N times as many."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softplc.api.debug import explain_board
from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.debug.nets import IO

SCALE = max(1, int(os.environ.get("SOFTPLC_FUZZ_SCALE", "1")))
MS = 1_000_000
PERIOD_MS = 10
PAUSED_CYCLES = 7  # wall-clock periods that pass while paused, before each step
CHECKS = 6  # pauses compared per net


@st.composite
def nets(draw: st.DrawFn) -> str:
    """A program text: 2..4 places, 2..5 transitions, each with an enabling delay and a
    timed firing drawn from 0 and a few periods (some not multiples of the period)."""
    places = [f"p{i}" for i in range(draw(st.integers(2, 4)))]
    lines = ["places:"]
    lines += [f"  {p}: {{tokens: {draw(st.integers(0 if i else 1, 2))}}}"
              for i, p in enumerate(places)]
    lines.append("transitions:")
    for i in range(draw(st.integers(2, 5))):  # a ring (tokens keep moving) plus random arcs
        ring = [places[i % len(places)]], [places[(i + 1) % len(places)]]
        pre, post = (sorted(set(arcs + draw(st.lists(st.sampled_from(places), max_size=1))))
                     for arcs in ring)
        delay = draw(st.sampled_from([0, 0, 10, 25, 40, 70]))
        duration = draw(st.sampled_from([0, 0, 20, 35, 60]))
        timing = (f", delay: {delay}ms" if delay else "") + \
                 (f", duration: {duration}ms" if duration else "")
        lines.append(f"  t{i}: {{from: [{', '.join(pre)}], to: [{', '.join(post)}]{timing}}}")
    return "\n".join(lines) + "\n"


class Stepper:
    """The loop's stop flag: pauses at once (a breakpoint that holds in every round), steps
    `first` scans, then at each pause keeps the board, lets PAUSED_CYCLES wall-clock periods
    pass and steps one scan, CHECKS times."""

    def __init__(self, loop: ScanLoop, first: int) -> None:
        self.loop, self.first, self.cycle, self.idle = loop, first, 0, 0
        self.boards: list[dict[str, Any]] = []
        self.last_scan = -1

    def is_set(self) -> bool:
        self.cycle += 1
        plc = self.loop.runner.plc
        if self.cycle == 1:
            self.loop.pending.append(ProgramCommand(Command.BREAK, symbol="when:not a"))
            return False
        if plc.debug.pause is None:
            return self.cycle > 10_000
        if plc.scan_count != self.last_scan:  # a new pause: keep its board, wait
            self.last_scan, self.idle = plc.scan_count, 0
            if self.first:  # the random scan to start from
                self.loop.pending.append(ProgramCommand(Command.STEP, value=self.first))
                self.first = 0
                return False
            self.boards.append(self.loop.document())
            return len(self.boards) > CHECKS
        self.idle += 1
        if self.idle == PAUSED_CYCLES:
            self.loop.pending.append(ProgramCommand(Command.STEP))
        return False

    def set(self) -> None:
        self.cycle = 10_000

    def wait(self, timeout: float | None = None) -> bool:
        return self.is_set()


@settings(max_examples=10 * SCALE, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(body=nets(), first=st.integers(1, 25))
def test_live_why_predicts_what_the_next_step_fires(tmp_path: Path, body: str,
                                                    first: int) -> None:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "t.yaml").write_text(f"program: t\nio_image: io.yaml\n{body}", encoding="utf-8")
    config = LoopConfig(program=str(tmp_path / "t.yaml"), start=True, period_ns=PERIOD_MS * MS)
    loop = ScanLoop(config, None, None, VirtualClock(0))  # type: ignore[arg-type]
    stepper = Stepper(loop, first)
    loop.run(stepper)  # type: ignore[arg-type]
    net = loop.runner.plc.net
    assert net is not None and len(stepper.boards) > CHECKS, body
    names = [t.name for t in net.transitions]
    for before, after in zip(stepper.boards, stepper.boards[1:], strict=False):
        assert after["scan_count"] == before["scan_count"] + 1
        counts = [(board["net_live"].get("fired_counts") or {}) for board in (before, after)]
        fired = {n for n in names if counts[1].get(n, 0) > counts[0].get(n, 0)}
        predicted = {n for n in names if explain_board(net, before, n).fires}
        assert predicted == fired, (f"scan {before['scan_count']}: why said {sorted(predicted)}"
                                    f" fire, the step fired {sorted(fired)}\n{body}")
        # The status countdown of a timed firing counts to the next scan's net time (the
        # 70 ms paused do not count): it ends in the step iff nothing is left.
        busy = [(board["net_live"].get("busy") or {}) for board in (before, after)]
        ending = {n for n, times in busy[0].items() if times["remaining_ms"] <= 0}
        ended = {n for n in busy[0] if n not in busy[1] or n in fired}
        assert ending == ended, (f"scan {before['scan_count']}: the countdown said "
                                 f"{sorted(ending)} end, the step ended {sorted(ended)}\n{body}")
