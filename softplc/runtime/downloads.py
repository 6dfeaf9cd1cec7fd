"""Downloads prepared off the scan: one worker thread in the scan process.

Owns: preparing downloaded programs on a background thread in arrival order (the compile
itself runs in the compile process, runtime/compileproc.py, and the scan thread loads its
result and builds the engine between scans, runtime/idlework.py, while this thread waits;
on a virtual clock this thread does all of it), holding the
commands that arrived after a download until it is decided (commands apply in the order they
were sent), and keeping that thread out of the scan's way: a short GIL switch interval while
a compile runs, so that a waking scan thread gets the interpreter back within a fraction of a
period, and a pace (`ScanPace`) that lets the compile run only while the scan thread waits
for its next slot.
Does not know: the PLC, the lifecycle, the channel, what compiling means.
"""

from __future__ import annotations

import sys
import threading
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from types import FrameType
from typing import Any, TypeVar

from softplc.core.lifecycle import Command
from softplc.core.snapshot import CommandRequest
from softplc.program.teardown import bury, burying
from softplc.runtime.idlework import IdleWork
from softplc.runtime.realtime import compile_thread

# While a compile runs, a waiting scan thread gets the GIL back after at most this long. The
# scan thread gives the GIL up at every blocking call and waits this long to get it back:
# measured with a 1 ms loop beside a compiling thread (2 s each, same run), overruns were
# 1048 at the default 5 ms, 136 at 200 µs, 42 at 50 µs, and 48 with no compile at all.
COMPILE_SWITCH_INTERVAL_S = 0.00005


_T = TypeVar("_T")
_OPEN = 1 << 62  # a pace nobody keeps: compiles never park


class ScanPace:
    """The scan thread says until when it will wait for its next slot; a compile thread runs
    only until then, and parks (without the interpreter lock) from then until the scan says
    it waits again.

    Why: threads of one CPython process share one interpreter lock. With the short switch
    interval alone, the two threads alternated every 50 µs while a big net compiled, so every
    scan took about twice as long and a 10,000-transition online change still missed 26-35
    slots at 1 ms (bench online_change). Parking only while a scan runs still let the compile
    hold the lock when the scan woke (missed slots under load). So the compile parks `margin`
    before the deadline, ahead of the clock's final spin: at its slot the scan finds the lock
    free. The compile thread looks at the pace at every Python function call it makes (a trace
    hook on that thread only, about twice its compile time).

    `now_ns` is the clock the deadlines are on; without one (a virtual clock, tests) the pace is
    open and compiles run freely."""

    __slots__ = ("_margin_ns", "_now_ns", "_turn", "_until_ns")

    def __init__(self, now_ns: Callable[[], int] | None = None, margin_ns: int = 0) -> None:
        self._now_ns = now_ns
        self._margin_ns = margin_ns
        self._until_ns = _OPEN
        self._turn = threading.Condition()

    def scanning(self) -> None:
        """From the scan thread, when its slot has come: a compile parks at its next call."""
        if self._now_ns is not None:
            self._until_ns = 0

    def waiting(self, deadline_ns: int) -> None:
        """From the scan thread, done with its slot: a compile may run until `margin` before
        `deadline_ns`."""
        if self._now_ns is not None:
            with self._turn:
                self._until_ns = deadline_ns - self._margin_ns
                self._turn.notify_all()

    def release(self) -> None:
        """No scan will come again (the loop ended): a parked compile goes on, freely."""
        with self._turn:
            self._now_ns, self._until_ns = None, _OPEN
            self._turn.notify_all()

    def hook(self, frame: FrameType, event: str, arg: Any) -> None:
        """sys.settrace hook of a compile thread: 'call' events only (it returns None, so no
        per-line tracing); a trace function is itself not traced."""
        now_ns = self._now_ns
        if now_ns is not None and now_ns() >= self._until_ns:
            with self._turn:
                while self._now_ns is not None and self._now_ns() >= self._until_ns:
                    self._turn.wait()

    def paced(self, work: Callable[[_T], Any]) -> Callable[[_T], Any]:
        """`work`, run on the calling thread at the scan's pace."""
        def run(argument: _T) -> Any:
            sys.settrace(self.hook)
            try:
                return work(argument)
            finally:
                sys.settrace(None)
        return run


@dataclass(frozen=True, slots=True)
class Decided:
    """A request whose turn has come: `net` for a compiled download, `error` for a refused
    one, neither for any other command."""

    request: CommandRequest
    net: Any = None  # what the compile function returned (the loop's Prepared download)
    error: BaseException | None = None


class DownloadQueue:
    """`put()` what the channel drained; `take()` at each scan boundary what may apply now."""

    def __init__(self, compile_program: Callable[[CommandRequest], Any],
                 switch_interval_s: float = COMPILE_SWITCH_INTERVAL_S,
                 pace: ScanPace | None = None, idle: IdleWork | None = None) -> None:
        self.pace = pace or ScanPace()
        self._idle = idle
        self._compile = self.pace.paced(compile_program)
        self._switch_interval_s = switch_interval_s
        self._default_interval_s = sys.getswitchinterval()
        self._queue: deque[tuple[CommandRequest, Future[Any] | None]] = deque()
        self._executor: ThreadPoolExecutor | None = None
        self._compiling = 0

    def put(self, requests: Iterable[CommandRequest]) -> None:
        for request in requests:
            future = None
            if request.command is Command.DOWNLOAD:
                future = self._pool().submit(self._compile, request)
                self._compiling += 1
                sys.setswitchinterval(self._switch_interval_s)
            self._queue.append((request, future))

    def take(self) -> list[Decided]:
        """The requests at the head of the queue that are decided, in arrival order; stops
        at the first download still compiling."""
        decided: list[Decided] = []
        finished = False
        while self._queue:
            request, future = self._queue[0]
            if future is not None and not future.done():
                break
            self._queue.popleft()
            if future is None:
                decided.append(Decided(request))
                continue
            self._compiling -= 1
            finished = True
            error = future.exception()
            decided.append(Decided(request, error=error) if error is not None
                           else Decided(request, net=future.result()))
        if finished and self._compiling == 0:  # not on every scan: only when the last one ends
            sys.setswitchinterval(self._default_interval_s)
        return decided

    def discard(self, box: list[Any]) -> None:
        """Let go of what `box` holds (a replaced net and its engine) a container at a time
        (program/teardown.py): between scans on the scan thread (runtime/idlework.py), else
        on the compile thread at the scan's pace. Freed at once, a 10,000-transition net and
        engine took 7.4 ms in one decref cascade. The box is emptied; the caller must hold
        no other reference."""
        held = box[:]
        box.clear()
        if self._idle is not None and self._idle.active:
            self._idle.submit(burying(held))
        else:
            self._pool().submit(self.pace.paced(bury), held)

    @property
    def waiting(self) -> int:
        """Requests not yet handed out (a download compiling and what queued behind it)."""
        return len(self._queue)

    def _pool(self) -> ThreadPoolExecutor:
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="compile",
                                                initializer=compile_thread)
        return self._executor

    def close(self) -> None:
        """Drop what is queued; a compile in progress finishes on its own and is discarded."""
        self.pace.release()  # a compile parked on a scan that will not come again goes on
        self._queue.clear()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None
        sys.setswitchinterval(self._default_interval_s)
