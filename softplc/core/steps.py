"""Work done a step at a time: a generator that yields between steps of bounded length and
returns its result.

Owns: the `Steps` type, `drain` (run them all, here and now) and `STEP` (how many items a
step handles where the items are cheap).
Why: an online change's last part (loading the compiled net, building and priming its
engine, planning the carry-over, freeing the replaced net) runs on the scan thread itself,
between scans, a step at a time (runtime/download.py), so that no second thread of the scan
process holds the interpreter lock when a slot comes. The same generators, drained, are the
plain functions: one implementation either way.
Does not know: threads, clocks, the scan.
"""

from __future__ import annotations

from collections.abc import Generator
from typing import Any, TypeVar

_T = TypeVar("_T")

Steps = Generator[None, None, _T]  # yields between steps, returns the result

# Items per step where each costs ~0.1-0.5 µs (a table entry, a place, an enabling check):
# at most ~130 µs a step, well inside the scan thread's STEP_NS (runtime/download.py).
STEP = 256


def drain(steps: Generator[Any, None, _T]) -> _T:
    """Every step now, on the calling thread; the result."""
    while True:
        try:
            next(steps)
        except StopIteration as done:
            result: _T = done.value
            return result
