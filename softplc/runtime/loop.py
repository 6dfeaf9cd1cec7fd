"""The real-time scan loop: the scan process of docs/design.md section 7.

Owns: absolute deadlines on the monotonic clock, skipped slots counted as overruns, the
cycle supervision (scans over period x watchdog, a cycle that starts that late: a stall),
measured here and judged by the PLC (core/judge.py's CycleWatchdog; a scan that never ends:
scanwatch.py); commands and HMI writes drained at the scan boundary, expired commands refused
unapplied; downloads stepped between scans on this thread (download.py: the job table), so
the scan only swaps, and a dry run only copies the PLC at its turn; the snapshot and the
board published after every scan (publisher.py: the board in the slack); retain captures
at scan boundaries; the cold or warm start; safe outputs, confirmed by the devices, on
every way out.
The boot program: bootkeeper.py; the process around the loop: scanproc.py.
Does not know: Modbus, HTTP (the communication process), terminals (the CLI).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from softplc.core.judge import NOTHING_OBSERVED, CycleWatchdog, Observed
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.problems import FaultCode
from softplc.core.snapshot import CommandReply, CommandRequest, Refusal, Status
from softplc.core.steps import Steps
from softplc.runtime import statusdoc, warmstart
from softplc.runtime.bootkeeper import BootKeeper
from softplc.runtime.clock import Clock, MonotonicClock, Schedule
from softplc.runtime.compileproc import CompileProcess
from softplc.runtime.config import LoopConfig as LoopConfig  # importable from here too
from softplc.runtime.download import Downloads, refusal_of
from softplc.runtime.eventlog import EventLog
from softplc.runtime.prepare import Prepared, Preparer, answering, boundary
from softplc.runtime.publisher import Publisher
from softplc.runtime.realtime import HelperThreads
from softplc.runtime.retain.writer import RetainWriter, capture
from softplc.runtime.runner import ScanRunner, open_drivers
from softplc.runtime.scanwatch import HangWatch
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.procs import Flag as Event
from softplc.runtime.shared.shm import SnapshotWriter
from softplc.runtime.stats import TimingStats
from softplc.runtime.trace import TraceWriter


class ScanLoop:
    """One PLC on a clock. `run()` until `stop` is set (or max_scans)."""

    def __init__(self, config: LoopConfig, channel: Channel | None, writer: SnapshotWriter | None,
                 clock: Clock | None = None, board: StatusBoard | None = None) -> None:
        self.config = config
        self.channel = channel
        self.writer = writer
        self.board = board
        # The snapshot and the board, the board after the scan (publisher.py).
        self.views = Publisher(writer, board, config.period_ns, lambda: self.document(),
                               lambda: self.status())
        self.budget_ns = int(config.period_ns * config.watchdog)
        self.watchdog = CycleWatchdog(
            self.budget_ns, config.watchdog_sensitivity, config.watchdog_hard_ns,
            config.stall_fault_ns if config.on_stall == "fault" else 0)
        self.hang = HangWatch(self.watchdog.hard_ns, self._hung,  # started on a real clock
                              lambda: self.clock.now_ns())  # the loop's, warm start included
        self.log = EventLog(config.first_event_seq)
        self.events = self.log.events  # what the board shows (statusdoc.py)
        self.start_mode = "cold"
        self.start_reason = "retain off (no state directory)"
        self.realtime = "normal scheduling"  # what scan_process_main obtained
        self.clock: Clock = clock or MonotonicClock(busy=config.realtime.busy_wait)
        self.stats = TimingStats()
        self.stalls, self.longest_gap_ns, self.internal_errors = 0, 0, 0
        self.summary = self.stats.summary()  # refreshed with the board, not every scan
        self.runner = ScanRunner(Plc.empty(), [],
                                 TraceWriter(config.trace) if config.trace else None)
        self.pending: list[ProgramCommand] = []
        # Downloads compile in a process of their own beside a real-time loop, and are
        # stepped on this thread between scans (download.py); on a virtual clock (tests,
        # simulation) all of it here, at the scan boundary: deterministic.
        real = isinstance(self.clock, MonotonicClock)
        self.compiler = CompileProcess(config) if real else None
        self.prep = Preparer(config, lambda: self.runner.plc.net, lambda: self._driver_specs,
                             self.compiler)
        self.downloads = Downloads(self.prep, threaded=real, realtime=config.realtime)
        self._paced = False  # run() steps downloads between scans; by hand: at the boundary
        self.helpers = HelperThreads(config.realtime)
        self._drain_ns = config.period_ns // 5  # a command's frames per scan (channel.drain)
        self._driver_specs: tuple[object, ...] = ()
        self.retain: RetainWriter | None = None
        self.retained_ns = 0
        self._prepared: dict[int, Prepared] = {}  # downloads handed to the scan, by request id
        self._retired: list[Any] = []  # a replaced net and its engine (scan_once)
        self.boot = BootKeeper(config, self.prep)
        net, self.analysis = self.boot.start(self.prep)  # loaded as `softplc run` compiled it
        warmstart.begin(self, net)
        self.runner.plc.debug.period_ns = config.period_ns  # a step is one period of net time
        if config.restarts:
            self._event(f"plc_restarted:{config.restarts}", 0)
        if config.paused_at_restart:  # not run on (docs/debug.md): start_reason says why
            self._event("plc_restarted_stopped:paused", 0)

    def _retain(self, now_ns: int) -> None:
        """At a scan boundary, when due: a consistent copy handed to the writer thread."""
        interval = self.config.retain_interval_ns
        if self.retain is None or interval <= 0 or now_ns - self.retained_ns < interval:
            return
        if (cap := capture(self.runner.plc, now_ns, self.runner.sim_plants())) is not None:
            self.retain.submit(cap, later=self._paced)  # run(): handed over in _slack
            self.retained_ns = now_ns

    # -- commands ---------------------------------------------------------------------------

    def _due_commands(self) -> list[ProgramCommand]:
        """The drained commands whose turn has come, in arrival order: downloads ready (off
        the scan, download.py) or refused with every problem listed; commands past their
        deadline refused unapplied (their sender has told its user so)."""
        commands = []
        for item in self.downloads.take(self._dry_run):
            req, prepared = item.request, item.prepared
            if req.deadline_ns and time.monotonic_ns() > req.deadline_ns:
                late_ms = (time.monotonic_ns() - req.deadline_ns) / 1e6
                self._reply(CommandReply(
                    req.id, False, f"{req.command.value} expired: not applied (its deadline "
                    f"passed {late_ms:.0f} ms before the scan could take it)",
                    self.runner.plc.state, expired=True, refusal=Refusal.EXPIRED))
                if prepared is not None:
                    prepared.discard()
                continue
            if item.reply is not None:  # a dry run's, built between scans since its turn
                self._reply(item.reply)
            elif req.command is not Command.DOWNLOAD:
                commands.append(ProgramCommand(req.command, online=req.online, id=req.id,
                                               symbol=req.symbol, value=req.value))
            elif item.error is not None or prepared is None:
                kind, message, problems = refusal_of(
                    item.error or RuntimeError("no program"), self.prep.relative)
                self._refuse(req, message, kind, problems)
            elif prepared.net.io.sizes != self.config.sizes:
                prepared.discard()
                why = f"the program's image sizes {prepared.net.io.sizes} differ from the runtime's"
                self._refuse(req, f"download refused: {why}", Refusal.SIZES, (why,))
            else:
                self._prepared[req.id] = prepared
                commands.append(ProgramCommand(
                    Command.DOWNLOAD, prepared.net, req.online, req.id, replace=req.replace,
                    engine=prepared.engine, plan=prepared.plan))
        return commands

    def _dry_run(self, prepared: Prepared) -> Steps[CommandReply] | None:
        """A dry run's turn: the PLC copied now, answered between scans (None: refused above)."""
        late = prepared.request.deadline_ns and time.monotonic_ns() > prepared.request.deadline_ns
        if late or prepared.net.io.sizes != self.config.sizes:
            return None
        return answering(prepared, boundary(self.runner.plc, self.config.sizes))

    def _refuse(self, req: CommandRequest, message: str, kind: Refusal,
                problems: tuple[str, ...]) -> None:
        self._reply(CommandReply(req.id, False, message, self.runner.plc.state,
                                 refusal=kind, problems=problems))

    def _reply(self, reply: CommandReply) -> None:
        if reply.id == 0 or self.channel is None:
            return  # startup commands come from the command line, not from a client
        self.channel.reply(reply, later=self._paced)  # run(): sent after the scan (_slack)

    def _slack(self) -> None:
        """After the scan and its snapshot: its board (publisher.py), its replies (a client
        told "applied" reads the new program), what the boot and retain writers are handed
        (woken in the scan, they take the interpreter lock from it), other threads off the
        scan's CPU."""
        try:
            self.views.out()  # the board first: what a reply tells, the board shows
        except Exception as exc:
            self._internal(f"publishing: {type(exc).__name__}: {exc}", self.clock.now_ns())
        try:
            if self.channel is not None:
                self.channel.send_held()
        except Exception as exc:
            self._internal(f"answering: {type(exc).__name__}: {exc}", self.clock.now_ns())
        self.boot.settle()
        if self.retain is not None:
            self.retain.settle()
        self.helpers.sweep()  # threads started since (downloads, devices): off the scan's CPU

    def _after(self, commands: Sequence[ProgramCommand],
               replies: Sequence[CommandReply]) -> None:
        """Swap in the devices of an accepted download, keep it as the boot program, answer."""
        accepted = None
        for reply in replies:
            prepared = self._prepared.pop(reply.id, None)
            if prepared is not None and reply.ok:
                accepted = prepared
            elif prepared is not None:
                prepared.discard()
        if accepted is not None:
            self.swap_drivers(accepted)
            self.boot.keep(accepted, later=self._paced)  # run(): settled after the scan
            self.analysis = accepted.analysis
            replies = [accepted.telling(r) for r in replies]
        elif any(c.command is Command.DOWNLOAD and c.id == 0 for c in commands):
            self.swap_drivers(None)
        for reply in replies:
            self._reply(reply)

    def swap_drivers(self, prepared: Prepared | None) -> None:
        net = self.runner.plc.net
        if net is None:
            return
        specs = tuple(net.io.drivers.values())
        if specs == self._driver_specs:
            if prepared is not None:  # opened for nothing: another download changed them
                prepared.close_drivers()
            return
        self._driver_specs = specs
        drivers = prepared.drivers if prepared is not None else None
        if drivers is None:  # the command line's program, or a race with another download
            drivers = open_drivers(net.io, self.config.seed, self.config.plant)
        self.runner.set_drivers(drivers)

    # -- the loop ---------------------------------------------------------------------------

    def scan_once(self, now_ns: int, observed: Observed = NOTHING_OBSERVED) -> bool:
        """One scan; True if it applied program commands (exempt from the watchdog: a
        download swaps the net and may open devices, not the program's execution time)."""
        if self._retired:  # replaced last scan: its transient references are gone by now
            self.downloads.discard(self._retired)
        requests, writes = self.channel.drain(self._drain_ns) if self.channel else ([], [])
        if requests:
            self.downloads.put(requests)
        if not self._paced and self.downloads.busy:  # scanned by hand (tests): no "between"
            self.downloads.work(None, self.clock.now_ns)
        commands = self.pending + self._due_commands()
        self.pending = []
        was_running = self.runner.plc.state is PlcState.RUNNING
        replaced = (self.runner.plc.net, self.runner.plc.engine) if commands else None
        result = self.runner.step(now_ns, commands, writes, observed=observed)
        if replaced is not None and replaced[0] is not None \
                and self.runner.plc.net is not replaced[0]:
            self._retired += replaced  # let go of off the scan thread, next scan
        if was_running and self.runner.plc.state is not PlcState.RUNNING:
            self._confirm_safe(now_ns)  # stop, kill, fault: the devices confirm before replies
        if commands or result.replies:  # the steady scan has nothing to swap or answer
            self._after(commands, result.replies)
        for name in result.events:
            self._event(name, now_ns)
        self.log.diagnostics(self.runner.plc.engine, self.runner.plc.scan_count, now_ns)
        return bool(commands)

    def _confirm_safe(self, now_ns: int, timeout_s: float = 0.2) -> None:
        """Safe outputs confirmed by the devices before the state is reported (stop, kill, a
        fault): a bounded wait in this one scan (exempt from the watchdog)."""
        if failed := self.runner.go_safe(now_ns, timeout_s):
            self._event("safe_unconfirmed:" + ",".join(failed), now_ns)

    def _event(self, name: str, now_ns: int) -> None:
        self.log.add(name, self.runner.plc.scan_count, now_ns)

    def document(self) -> dict[str, Any]:  # what `softplc status` and the HTTP API show
        return statusdoc.document(self)

    def status(self) -> Status:
        return statusdoc.status(self)

    def run(self, stop: Event | None = None, safe: Callable[[], object] = lambda: None) -> None:
        if self.compiler is not None:
            self.compiler.start()  # ready before the first download, from the thread that stays
        self.boot.started["loop_ns"] = time.monotonic_ns()  # the first scan: a period later
        self._paced = True
        try:
            self._run(stop)
        finally:
            self._paced = False
        self.shutdown(safe)

    def _run(self, stop: Event | None) -> None:
        period = self.config.period_ns
        schedule = Schedule(self.clock, period)
        spin_ns = self.clock.spin_ns if isinstance(self.clock, MonotonicClock) else 0
        if isinstance(self.clock, MonotonicClock):
            self.hang.start()
        try:
            while (stop is None or not stop.is_set()) and (
                    self.config.max_scans is None
                    or self.runner.plc.scan_count < self.config.max_scans):
                deadline = schedule.deadline_ns
                if self.downloads.busy:  # steps done before the clock's final spin, on its time
                    self.downloads.work(deadline - spin_ns, self.clock.now_ns)
                reached = schedule.wait()
                late = reached - deadline
                observed = self._stall(late) if late > self.budget_ns else NOTHING_OBSERVED
                self.hang.begin(reached)
                handled_commands = self._guarded_scan(reached, observed)
                if self.hang.end():  # faulted meanwhile: what the scan wrote goes safe again
                    self._confirm_safe(self.clock.now_ns())
                self._publish(reached)
                done = self.clock.now_ns()
                exec_ns = done - reached  # I/O, round, snapshot, retain (the board: _slack)
                if exec_ns > self.budget_ns or self.watchdog.over:
                    self._watchdog(exec_ns, done, watched=not handled_commands)
                self.stats.record(exec_ns, late, skipped=schedule.advance(done))
                self._slack()
        finally:
            self._slack()
            self.hang.close()

    def _stall(self, late_ns: int) -> Observed:
        """A cycle that started more than the watchdog budget late: the process was paused or
        starved, and for that long nothing read inputs or wrote outputs."""
        self.stalls += 1
        self.longest_gap_ns = max(self.longest_gap_ns, late_ns)
        self._event(f"stall:{late_ns // 1_000_000}ms", self.clock.now_ns())
        reason = self.watchdog.stall(late_ns)
        return Observed(stall=reason) if reason else NOTHING_OBSERVED

    def _guarded_scan(self, now_ns: int, observed: Observed) -> bool:
        """scan_once, and whatever it raises outside the pure scan (the channel, the download
        queue, a swap of devices) faults the PLC with safe outputs instead of ending the
        scan process: the PLC keeps serving status and commands."""
        try:
            return self.scan_once(now_ns, observed)
        except Exception as exc:
            self._internal(f"scan shell: {type(exc).__name__}: {exc}", now_ns)
            return True

    def _publish(self, now_ns: int) -> None:
        try:
            if refresh := self.views.refreshing(self.stats.scans):  # percentiles: ~20 us
                self.summary = self.stats.summary()
            self.views.scanned(self.runner.plc, refresh, later=self._paced)
            self._retain(now_ns)
        except Exception as exc:
            self._internal(f"publishing: {type(exc).__name__}: {exc}", now_ns)

    def _internal(self, reason: str, now_ns: int) -> None:
        self.internal_errors += 1
        print(f"softplc: internal error, PLC faulted: {reason}", file=sys.stderr, flush=True)
        plc = self.runner.plc
        plc.fault(FaultCode.INTERNAL, None, reason)
        plc.drive_safe()
        self._confirm_safe(now_ns)
        self._event("plc_fault:internal", now_ns)

    def _watchdog(self, exec_ns: int, now_ns: int, watched: bool) -> None:
        """CycleWatchdog's rule; a scan that handled commands (a download) is not counted."""
        plc = self.runner.plc
        if reason := self.watchdog.check(plc.scan_count - 1, exec_ns,
                                         plc.state is PlcState.RUNNING, watched):
            for name in self.runner.judge_now(Observed(overrun=reason), now_ns):
                self._event(name, now_ns)

    def _hung(self, elapsed_ns: int) -> None:
        """On the watchdog thread, the scan thread still in one scan: fault and status now."""
        plc, now_ns = self.runner.plc, self.clock.now_ns()
        self._event(f"scan_hung:{elapsed_ns // 1_000_000}ms", now_ns)
        reason = self.watchdog.hung(plc.scan_count, elapsed_ns)
        for name in self.runner.judge_now(Observed(overrun=reason), now_ns):
            self._event(name, now_ns)
        if self.writer is not None:
            self.writer.publish(plc.image, self.status())
        if self.board is not None:
            self.board.publish(self.document())

    def shutdown(self, safe: Callable[[], object] = lambda: None) -> None:
        """Outputs to their safe values, written through the drivers and confirmed (then said:
        `safe`); the final retain snapshot written synchronously (and said); then close."""
        self.summary = self.stats.summary()
        plc = self.runner.plc
        now_ns = self.clock.now_ns()
        # Captured before the outputs go safe: a warm restart resumes what the program drove.
        final = capture(plc, now_ns, self.runner.sim_plants()) if self.retain is not None else None
        plc.drive_safe()
        self._confirm_safe(now_ns, timeout_s=0.5)
        if self.writer is not None:
            self.writer.publish(plc.image, self.status())
        safe()
        self.runner.close()
        self.downloads.close()
        if self.compiler is not None:
            self.compiler.close()
        for prepared in self._prepared.values():
            prepared.discard()
        self.boot.close()
        if self.retain is not None:
            # Bounded: SIGTERM must end everything within the supervisor's STOP_S.
            outcome = self.retain.stop(final, timeout_s=1.0)
            if self.channel is not None:  # a real scan process: say it where people look
                print(f"softplc: {outcome}", file=sys.stderr, flush=True)
        if self.board is not None:
            self.board.publish(self.document())
