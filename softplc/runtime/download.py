"""A download as one job with one owner: a table of stages that the scan thread steps between
its scans (docs/design.md section 12, the download job).

Owns: the stages of every download and the table of the stages each may go to; stepping them
without blocking (the compile process's answer polled, the net loaded and its engine built a
step at a time, the devices' opening polled; at its turn, a dry run's answer built from the
PLC copied at that boundary, a stale carry plan made again); the order of commands (a command
sent after a download waits until the download is decided, except stop and kill, which are
never held: the downloads still being prepared ahead of one are withdrawn); burials.
What blocks runs on one helper thread, and only that: the exchange with the compile process
(runtime/compileproc.py) and the opening of a new io image's devices and the staging of the
boot program (runtime/prepare.py). The steps' costs: runtime/steplog.py.
Does not know: the PLC, the lifecycle, the channel, what compiling means (runtime/prepare.py).
"""

from __future__ import annotations

import gc
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.core.snapshot import DOWNLOAD_REFUSED, CommandReply, CommandRequest, Refusal
from softplc.core.steps import Steps, drain
from softplc.devices.driver import DeviceError
from softplc.program.teardown import burying
from softplc.program.wire import Piece
from softplc.runtime.bootkeeper import BootNotKept
from softplc.runtime.prepare import (
    AnalysisRefused,
    Built,
    CompilerFailed,
    DownloadRefused,
    Prepared,
    Preparer,
    describe_error,
)
from softplc.runtime.realtime import NORMAL, Realtime, background_thread
from softplc.runtime.steplog import StepLog


class Stage(Enum):
    COMPILING = "compiling"  # compiled and analysed by the compile process (or here)
    LOADING = "loading"  # its net loaded, engine built and primed, carry plan: steps here
    OPENING = "opening"  # new devices opened and the boot program staged: the helper thread
    PLANNING = "planning"  # its carry plan made again (another net runs now): steps here
    READY = "ready"  # its turn at the next boundary: handed to the scan (a dry run: DESCRIBING)
    DESCRIBING = "describing"  # a dry run's answer, from the PLC copied at its turn: steps here
    ANSWERED = "answered"  # a dry run's reply, handed to the scan to send
    REFUSED = "refused"  # handed to the scan to be answered, with its typed error


# The job table: the stages each stage may go to. Nothing else moves a job.
TABLE: dict[Stage, frozenset[Stage]] = {
    Stage.COMPILING: frozenset({Stage.LOADING, Stage.REFUSED}),
    Stage.LOADING: frozenset({Stage.OPENING, Stage.READY, Stage.REFUSED}),
    Stage.OPENING: frozenset({Stage.READY, Stage.REFUSED}),
    Stage.PLANNING: frozenset({Stage.READY, Stage.REFUSED}),
    Stage.READY: frozenset({Stage.PLANNING, Stage.DESCRIBING}),  # at its turn (Downloads.take)
    Stage.DESCRIBING: frozenset({Stage.ANSWERED, Stage.REFUSED}),
    Stage.ANSWERED: frozenset(),
    Stage.REFUSED: frozenset(),
}

# Commands never held behind a download still being prepared: a stop or a kill is applied at
# the next scan boundary, and the downloads queued before it are withdrawn (refused, named).
URGENT = frozenset({Command.STOP, Command.KILL})


class Withdrawn(DownloadRefused):
    """A download given up before it was decided: a stop or kill sent after it came first,
    or the loop ended."""


@dataclass(slots=True)
class DownloadJob:
    """One download from request to READY or REFUSED. `step()` on the scan thread."""

    request: CommandRequest
    prep: Preparer
    helper: Callable[[Callable[[], Any]], Future[Any]]
    stage: Stage = Stage.COMPILING
    prepared: Prepared | None = None
    error: BaseException | None = None
    reply: CommandReply | None = None  # a dry run's, once ANSWERED
    _waiting: Future[Any] | None = None
    _steps: Steps[Any] | None = None
    _gc_was: bool = field(default=False)

    @property
    def decided(self) -> bool:
        return self.stage in (Stage.READY, Stage.ANSWERED, Stage.REFUSED)

    def _to(self, stage: Stage) -> None:
        assert stage in TABLE[self.stage], f"download job: {self.stage} -> {stage}"
        self.stage = stage

    def refuse(self, error: BaseException) -> None:
        self._close_steps()
        prepared, waiting = self.prepared, self._waiting
        if prepared is not None:
            prepared.discard()
            if waiting is not None and not waiting.done():
                # Withdrawn while the helper thread opens its devices or stages its boot
                # program: what that work opens or writes is let go of when it ends.
                waiting.add_done_callback(lambda _: prepared.discard())
        self._waiting = None
        self.error = error
        self._to(Stage.REFUSED)

    def step(self) -> bool:
        """One bounded step; False when the job waits for the helper thread (or is decided)."""
        try:
            return self._step()
        except Exception as exc:  # the download's own failure: refused with it
            self.refuse(exc)
            return True

    def _step(self) -> bool:
        if self.stage is Stage.COMPILING:
            return self._compiling()
        if self.stage is Stage.LOADING:
            return self._loading()
        if self.stage is Stage.OPENING:
            return self._opening()
        if self.stage in (Stage.PLANNING, Stage.DESCRIBING):
            return self._turn_step()
        return False

    def at_turn(self, stage: Stage, steps: Steps[Any]) -> None:
        """READY at the head of the queue, at a scan boundary: `steps` (its plan again, or
        a dry run's answer) to be stepped between scans before it is handed out."""
        self._steps = steps
        self._to(stage)

    def _turn_step(self) -> bool:
        assert self._steps is not None
        try:
            next(self._steps)
        except StopIteration as done:
            self._steps, answered = None, self.stage is Stage.DESCRIBING
            self.reply = done.value if answered else None
            self._to(Stage.ANSWERED if answered else Stage.READY)
        return True

    def _compiling(self) -> bool:
        if self.prep.remote is None:  # a virtual clock: compiled here, deterministically
            net = self.prep.compile(self.request)
            self._load(net, self.prep.analyse(net))
            return True
        if self._waiting is None:
            remote, request = self.prep.remote, self.request
            self._waiting = self.helper(lambda: remote.build(request))
            return False
        if not self._waiting.done():
            return False
        built: Built = self._waiting.result()  # raises the refusal: step() refuses with it
        self._waiting = None
        self.prep.bundle_roots.update(built.bundle_roots)
        self._load(built.net, built.analysis, built.boot_file)
        return True

    def _load(self, net: CompiledNet | tuple[Piece, ...], analysis: dict[str, Any] | None,
              boot_file: bytes | None = None) -> None:
        self._steps = self.prep.finishing(self.request, net, analysis, boot_file)
        # Loading allocates a net's worth of objects: a full collection meanwhile holds the
        # interpreter for tens of ms over the whole heap. Off while loading; what was built
        # is frozen at the end (out of every later collection).
        self._gc_was = gc.isenabled()
        gc.disable()
        self._to(Stage.LOADING)

    def _loading(self) -> bool:
        assert self._steps is not None
        try:
            next(self._steps)
            return True
        except StopIteration as done:
            self._steps = None
            self._gc_restore(freeze=True)
            self.prepared = done.value
        assert self.prepared is not None
        work = self.prep.opening(self.prepared)
        if work is None:
            self._to(Stage.READY)
        else:
            self._waiting = self.helper(work)
            self._to(Stage.OPENING)
        return True

    def _opening(self) -> bool:
        assert self._waiting is not None and self.prepared is not None
        if not self._waiting.done():
            return False
        self._waiting.result()  # raises the refusal: step() refuses with it
        self._waiting = None
        self._to(Stage.READY)
        return True

    def _gc_restore(self, freeze: bool) -> None:
        if freeze:
            gc.freeze()
        if self._gc_was:
            gc.enable()
        self._gc_was = False

    def _close_steps(self) -> None:
        if self._steps is not None:
            self._steps.close()
            self._steps = None
            self._gc_restore(freeze=False)


@dataclass(frozen=True, slots=True)
class Decided:
    """A request whose turn has come: `prepared` for a download ready to apply, `error` for a
    refused one, neither for any other command."""

    request: CommandRequest
    prepared: Prepared | None = None
    error: BaseException | None = None
    reply: CommandReply | None = None  # a dry run's answer, to send as it is


# At a dry run's turn, on the scan thread at the boundary: its answer's steps, from the PLC
# copied now; None: handed out as any download (the loop refuses or expires it).
Turn = Callable[[Prepared], Steps[CommandReply] | None]


class Downloads:
    """`put()` what the channel drained; `work()` between scans; `take()` at each scan
    boundary what may apply now, in arrival order."""

    def __init__(self, prep: Preparer, threaded: bool = True, realtime: Realtime = NORMAL) -> None:
        """`threaded`: blocking parts on the helper thread (a real clock, kept off a pinned
        scan's CPU); else here and now (a virtual clock: simulation and tests, deterministic)."""
        self.prep, self._realtime, self._threaded = prep, realtime, threaded
        self._queue: deque[CommandRequest | DownloadJob] = deque()
        self._burials: deque[Steps[None]] = deque()
        self._executor: ThreadPoolExecutor | None = None
        self.log = StepLog()  # status: download_steps

    def put(self, requests: Iterable[CommandRequest]) -> None:
        for request in requests:
            if request.command is Command.DOWNLOAD:
                self._queue.append(DownloadJob(request, self.prep, self._helper))
            elif request.command in URGENT:
                self._withdraw_before(request)
            else:
                self._queue.append(request)

    def _withdraw_before(self, urgent: CommandRequest) -> None:
        """The downloads still being prepared ahead of `urgent` are withdrawn (refused, saying
        why): nothing then holds it, and what was sent before it still applies before it."""
        for item in self._queue:
            if isinstance(item, DownloadJob) and not item.decided:
                item.refuse(Withdrawn(f"withdrawn: a {urgent.command.value}, sent after it, "
                                      "was applied first (a stop or kill is never held behind "
                                      "a download)"))
        self._queue.append(urgent)

    @property
    def busy(self) -> bool:  # work to step between scans
        return bool(self._burials) or any(
            isinstance(item, DownloadJob) and not item.decided for item in self._queue)

    def work(self, until_ns: int | None, now_ns: Callable[[], int]) -> None:
        """Steps of every job in arrival order, then of the burials, while one can still end
        before `until_ns` (None: until each waits or is done), each noted in `log`."""
        limit = None if until_ns is None else until_ns - STEP_NS
        for item in list(self._queue):
            while isinstance(item, DownloadJob) and not item.decided:
                if limit is not None and (began := now_ns()) >= limit:
                    return
                stage, stepped = item.stage.value, item.step()
                if limit is not None:  # what it cost, against the scan's time (steplog.py)
                    self.log.note(stage, began, now_ns(), until_ns)
                if not stepped:
                    break
        while self._burials and (limit is None or (began := now_ns()) < limit):
            if next(self._burials[0], self) is self:  # that burial is done
                self._burials.popleft()
            if limit is not None:
                self.log.note("burying", began, now_ns(), until_ns)

    def take(self, turn: Turn = lambda _: None) -> list[Decided]:
        """The requests at the head of the queue that are decided, in arrival order; stops
        at the first download not yet decided. A download whose turn comes first gets its
        carry plan again if another net runs now, a dry run its answer (`turn`), stepped
        between scans (on a virtual clock: here, now); at most one download is handed out
        per boundary (the next one is planned against it)."""
        decided: list[Decided] = []
        while self._queue:
            item = self._queue[0]
            if isinstance(item, DownloadJob):
                if item.stage is Stage.READY and self._at_turn(item, turn):
                    while not self._threaded and not item.decided and item.step():
                        pass
                if not item.decided:
                    break
                if item.reply is not None:  # a dry run's net and engine: freed between scans
                    box, item.prepared = [item.prepared], None
                    self.discard(box)
                decided.append(Decided(item.request, item.prepared, item.error, item.reply))
            else:
                decided.append(Decided(item))
            self._queue.popleft()
            if isinstance(item, DownloadJob) and self._threaded and item.stage is Stage.READY \
                    and not item.request.dry_run and self._queue \
                    and isinstance(self._queue[0], DownloadJob):
                break
        return decided

    def _at_turn(self, job: DownloadJob, turn: Turn) -> bool:
        assert job.prepared is not None
        dry = job.request.dry_run  # its answer, else its carry plan if another net runs now
        steps: Steps[Any] | None = turn(job.prepared) if dry \
            else self.prep.replanning(job.prepared)
        if steps is not None:
            job.at_turn(Stage.DESCRIBING if dry else Stage.PLANNING, steps)
        return steps is not None

    def stage(self, request_id: int) -> Stage | None:
        """Where a download is (status, tests)."""
        return next((item.stage for item in self._queue if isinstance(item, DownloadJob)
                     and item.request.id == request_id), None)

    @property
    def waiting(self) -> int:  # requests not yet handed out (downloads and what queued behind)
        return len(self._queue)

    def discard(self, box: list[Any]) -> None:
        """Let go of what `box` holds (a replaced net and its engine) a container at a time,
        between scans (program/teardown.py; freed at once, a 10,000-transition net and engine
        took 7.4 ms in one decref cascade). Emptied; the caller must hold no other reference."""
        held, box[:] = box[:], []
        burial = burying(held)
        if self._threaded:
            self._burials.append(burial)
        else:
            drain(burial)

    def _helper(self, work: Callable[[], Any]) -> Future[Any]:
        """`work` on the helper thread (a real clock), or done now (a virtual clock)."""
        if not self._threaded:
            future: Future[Any] = Future()
            try:
                future.set_result(work())
            except Exception as exc:
                future.set_exception(exc)
            return future
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="download",
                                                initializer=background_thread,
                                                initargs=(self._realtime,))
        return self._executor.submit(work)

    def close(self) -> None:
        """The loop ended: what is queued is dropped (its senders time out, as the channel
        ends too); what the helper thread does finishes on its own and is let go of."""
        for item in self._queue:
            if isinstance(item, DownloadJob) and not item.decided:
                item.refuse(Withdrawn("withdrawn: the scan loop ended"))
        self._queue.clear()
        for burial in self._burials:
            burial.close()
        self._burials.clear()
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None


def refusal_of(error: BaseException,
               relative: Callable[[str], str]) -> tuple[Refusal, str, tuple[str, ...]]:
    """A refused download's kind, message and problems (paths as the sender knows them)."""
    if isinstance(error, AnalysisRefused):
        return (Refusal.ANALYSIS, f"{DOWNLOAD_REFUSED} by the analysis gate (--verify refuse):\n"
                + "\n".join(error.findings), error.findings)
    if isinstance(error, ProgramError):
        text = relative(str(error))
        return (Refusal.PROGRAM, f"{DOWNLOAD_REFUSED}:\n{text}",
                tuple(line.strip() for line in text.splitlines() if line.strip()))
    kind = (Refusal.WITHDRAWN if isinstance(error, Withdrawn)
            else Refusal.BOOT if isinstance(error, BootNotKept)
            else Refusal.COMPILER if isinstance(error, CompilerFailed)
            else Refusal.DEVICE if isinstance(error, DeviceError | ValueError | OSError)
            else Refusal.COMPILER)
    why = relative(describe_error(error))
    return kind, f"{DOWNLOAD_REFUSED}: {why}", (why,)


# The longest a step takes (a net's piece loaded ~150 µs, a table block ~200 µs, loaded twice
# that; steplog.py measures them): no step starts later than this before the loop's limit.
STEP_NS = 300_000
