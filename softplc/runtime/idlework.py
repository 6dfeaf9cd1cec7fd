"""Work the scan thread does between its scans, a step at a time.

Owns: the queue of such work (generators of core/steps.py: an online change's loading of the
compiled net, its engine, its carry plan; the burial of the net it replaced) and running its
steps until a time the loop gives, on the scan thread; handing each result or exception to
the thread that asked (a Future).
Why on the scan thread: threads of one CPython process share one interpreter lock. A compile
thread that builds the engine beside the scan holds that lock whenever the kernel preempts it
(another process on its CPU, the scan's own CPU while the scan busy-waits), and the scan then
waits for a thread that does not run: slots missed that no pacing of that thread can
prevent. Done here, nothing but the scan's own steps runs in the scan process's interpreter,
and each step ends before the slot that follows (STEP_NS).
Does not know: what the work is, the PLC, the clock's kind.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

from softplc.core.steps import Steps, drain

_T = TypeVar("_T")

# The longest a step takes (a piece of a net loaded: ~150 µs, a table block: ~200 µs, on a
# loaded machine twice that): no step starts later than this before the loop's limit.
STEP_NS = 300_000


class LoopEnded(RuntimeError):
    """The scan loop ended before the work was done."""


class IdleWork:
    """`submit` from any thread; `run` on the scan thread after each scan, from `start()`
    (the loop runs) to `close()` (it ended)."""

    def __init__(self, now_ns: Callable[[], int]) -> None:
        self._now_ns = now_ns
        self._jobs: deque[tuple[Steps[Any], Future[Any]]] = deque()
        self._lock = threading.Lock()
        self._closed = False
        self.active = False  # a loop runs the steps: set by start(), cleared by close()

    def start(self) -> None:
        self.active = not self._closed

    def finish(self, steps: Steps[_T]) -> _T:
        """`steps` to their end: on the scan thread while the loop runs, else here (a loop
        scanned by hand, as tests do, never runs queued steps)."""
        # On the scan thread: this thread waits for the result without the interpreter lock.
        return self.submit(steps).result() if self.active else drain(steps)

    def submit(self, steps: Steps[_T]) -> Future[_T]:
        future: Future[_T] = Future()
        with self._lock:
            if self._closed:
                steps.close()
                future.set_exception(LoopEnded("the scan loop has ended"))
            else:
                self._jobs.append((steps, future))
        return future

    @property
    def pending(self) -> int:
        return len(self._jobs)

    def run(self, until_ns: int) -> None:
        """On the scan thread: steps of the queued work while a step still ends before
        `until_ns` (at least STEP_NS before it)."""
        jobs, now_ns = self._jobs, self._now_ns
        limit = until_ns - STEP_NS
        while jobs and now_ns() < limit:
            steps, future = jobs[0]
            try:
                next(steps)
            except StopIteration as done:
                self._finish(future, done.value, None)
            except Exception as exc:  # the work's own failure: its requester is told
                self._finish(future, None, exc)

    def _finish(self, future: Future[Any], value: Any, error: Exception | None) -> None:
        with self._lock:
            self._jobs.popleft()
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(value)

    def close(self) -> None:
        """No scan will come again: queued work is dropped, its requesters told."""
        with self._lock:
            self._closed, self.active = True, False
            jobs, self._jobs = list(self._jobs), deque()
        for steps, future in jobs:
            steps.close()
            future.set_exception(LoopEnded("the scan loop ended before the download was "
                                           "loaded"))
