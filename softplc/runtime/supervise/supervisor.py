"""The processes of `softplc run`: start the scan process and the service processes (one each
for Modbus, HTTP and OPC UA, those that are on), watch them, heal them, and stop them all
with outputs driven safe.

Owns: process start order; the shared-memory segments (they outlive a scan process, so the
service processes keep serving across a restart); restarting a dead scan process warm from
the newest retain snapshot and the boot program, with backoff, at most SCAN_RESTARTS times in
RESTART_WINDOW_S, then giving up (GaveUp), its boot program compiled meanwhile
(supervise/startprog.py), and STOPPED if it died paused at a breakpoint
(its last status board says so; docs/debug.md); restarting a dead service process within
the same kind of budget, each its own; stopping everything within STOP_S in every state, also
while a child is still starting: the scan process first (outputs safe, confirmed by the
devices), then every service process at once, so no service goes away while an output is
still on.
Does not know: what a scan does, what a snapshot holds, the console and exit codes
(runcmd.py), what killed runs leave in /dev/shm (leftovers.py).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import multiprocessing as mp
import os
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from softplc.core.errors import SoftplcError
from softplc.core.image import ImageSizes
from softplc.runtime.config import LoopConfig
from softplc.runtime.eventlog import newest_seq
from softplc.runtime.realtime import Realtime, keep_off_scan_cpu
from softplc.runtime.scanproc import scan_process_main
from softplc.runtime.serve.comm import CommConfig, comm_process_main, modbus_limits, service_groups
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.procs import ReadySignal, StopFlag
from softplc.runtime.shared.shm import SnapshotWriter
from softplc.runtime.supervise.leftovers import SHM_PREFIX, record_semaphores
from softplc.runtime.supervise.startprog import BootForms

SCAN_RESTARTS: Final = 5  # scan process restarts allowed within RESTART_WINDOW_S
COMM_RESTARTS: Final = 5  # restarts of each service process allowed within RESTART_WINDOW_S
RESTART_WINDOW_S: Final = 60.0
BACKOFF_S: Final = (0.0, 0.5, 1.0, 2.0, 4.0)  # by restarts within BACKOFF_WINDOW_S
BACKOFF_WINDOW_S: Final = 10.0  # a scan process that ran this long restarts without delay
STOP_S: Final = 2.0  # SIGTERM/SIGINT: every process gone within this (then SIGKILL)
# At a stop, how long the supervisor waits for the scan's "safe" before it stops the
# service processes anyway: the confirmed safe write is bounded by 0.5 s
# (ScanLoop.shutdown), plus the scan in progress.
SAFE_WAIT_S: Final = 1.0


class GaveUp(SoftplcError, RuntimeError):
    """The scan process died too often: the supervisor stops instead of looping."""


# What each service process is called in process lists (at most procs.COMM_BYTES) and in
# what the supervisor says.
_TITLES: Final = {"modbus": ("softplc-modbus", "Modbus process"),
                  "modbus-tls": ("softplc-mbtls", "Modbus/TCP Security process"),
                  "http": ("softplc-http", "HTTP process"),
                  "opcua": ("softplc-opcua", "OPC UA process"),
                  "sparkplug": ("softplc-spb", "Sparkplug process")}


@dataclass(eq=False)
class ServiceProcess:
    """One service process (comm.service_groups): its configuration, stop flag, process
    and restart history."""

    name: str
    config: Any  # a CommConfig, or what `main` takes (sparkplug/config.py SparkplugConfig)
    stop: StopFlag = field(default_factory=StopFlag)
    proc: Any = None
    restarts: deque[float] = field(default_factory=deque)
    main: Callable[..., None] = comm_process_main  # or the entry the CLI resolved (sparkplug)

    @property
    def title(self) -> str:
        return _TITLES[self.name][1]


class Supervisor:
    """The scan process and the service processes of one PLC. `scan_main` and its
    `scan_args` (after the standard ones) let the benchmark run an instrumented scan loop
    under the same start order, names and stop events."""

    def __init__(self, loop_config: LoopConfig, comm_config: CommConfig, *,
                 scan_main: Callable[..., None] = scan_process_main,
                 scan_args: tuple[Any, ...] = (), tag: str | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.ctx = mp.get_context("spawn")
        self.channel = Channel(ctx=self.ctx)
        self.tag = tag or f"{SHM_PREFIX}{os.getpid()}"
        self.shm_name, self.board_name = f"{self.tag}_image", f"{self.tag}_board"
        self.stop_scan = StopFlag()
        self.loop_config, self.comm_config = loop_config, comm_config
        self.scan_main, self.scan_args = scan_main, scan_args
        self.scan: Any = None
        self.services = [ServiceProcess(name, config)
                         for name, config in service_groups(comm_config).items()]
        self._scan_says: ReadySignal | None = None  # "ready", then "safe" at a stop
        self._stopping: Callable[[], bool] = lambda: False
        self.clock = clock
        self.scan_restarts: deque[float] = deque()  # when, within the window
        self.restarts = 0  # scan process restarts in this run, for status
        self.restart_reason = ""
        self.paused_at_restart = ""  # the pause a dead scan process was in (docs/debug.md)
        self.event_seq = 0  # the last event number a dead scan process showed on the board
        self._restart_due: float | None = None
        self.final: dict[str, Any] = {}
        self.segment: SnapshotWriter | None = None
        self.board: StatusBoard | None = None
        self.boot_forms = BootForms(self.ctx)  # the boot program compiled for a scan process

    @property
    def modbus(self) -> Any:
        """The Modbus process, None when not running."""
        return self.process("modbus")

    @property
    def http(self) -> Any:
        """The HTTP process (API and page), None when not running."""
        return self.process("http")

    @property
    def opcua(self) -> Any:
        """The OPC UA process, None when not running."""
        return self.process("opcua")

    def process(self, name: str) -> Any:
        """The service process `name` (comm.service_groups), None when not running."""
        return next((s.proc for s in self.services if s.name == name), None)

    def pids(self) -> str:
        """The service processes and their pids, in words: "Modbus process pid 12, ..."."""
        return ", ".join(f"{s.title} pid {s.proc.pid if s.proc is not None else '-'}"
                         for s in self.services) or "no service process"

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Supervisor:
        """`softplc run`'s flags. Raises ValueError for --rt-priority / --scan-cpu."""
        sizes = ImageSizes()
        # Downloads may reference files under root only: the program's folder's parent (its
        # programs/ and io_images/ beside each other), else that of --programs-dir, else here.
        programs_dir = getattr(args, "programs_dir", None)
        root = (Path(args.program).resolve().parent.parent if args.program
                else Path(programs_dir).resolve().parent if programs_dir else Path.cwd())
        loop_config = LoopConfig(
            program=args.program, start=args.start, period_ns=args.period, plant=args.plant,
            seed=args.seed, trace=args.trace, watchdog=args.watchdog, root=str(root),
            programs_dir=getattr(args, "programs_dir", None),
            sizes=sizes, state_dir=args.state_dir,
            retain_interval_ns=getattr(args, "retain_interval", 1_000_000_000),
            warm_start=getattr(args, "warm_start", "run"),
            boot_policy=getattr(args, "boot_policy", None) or "warm",  # runcmd resolves it
            boot_policy_source=getattr(args, "boot_policy_source", ""),
            on_stall=getattr(args, "on_stall", "fault"), verify=getattr(args, "verify", "warn"),
            stall_fault_ns=getattr(args, "stall_fault_after", 3_000_000_000),
            watchdog_sensitivity=getattr(args, "watchdog_sensitivity", 3),
            watchdog_hard_ns=getattr(args, "watchdog_hard", 3_000_000_000),
            realtime=Realtime(getattr(args, "rt_priority", None), getattr(args, "scan_cpu", None),
                              getattr(args, "busy_wait", False)))
        comm_config = CommConfig(modbus=args.modbus, api=args.api, state_dir=args.state_dir,
                                 sizes=sizes, modbus_writes=getattr(args, "modbus_writes", "open"),
                                 opcua=getattr(args, "opcua", None),
                                 modbus_tls=getattr(args, "modbus_tls", None),
                                 **modbus_limits(args))
        supervisor = cls(loop_config, comm_config)
        if (sparkplug := getattr(args, "sparkplug", None)) is not None:  # cli resolved it
            supervisor.services.append(ServiceProcess("sparkplug", sparkplug, main=sparkplug.main))
        return supervisor

    def start(self, timeout_s: float = 30.0,
              stopping: Callable[[], bool] = lambda: False) -> None:
        """Every process, each waited for until it serves. Once `stopping()` (a signal came)
        it waits no longer: the caller's stop() follows, and a scan process already driving
        outputs must not stay on for the seconds the services take to start (OPC UA)."""
        self._stopping = stopping
        # The segments belong to the supervisor: they outlive a scan process, so the
        # service processes keep their mappings (and say "stale") across a restart.
        self.segment = SnapshotWriter.create(self.loop_config.sizes, self.shm_name)
        self.board = StatusBoard.create(self.board_name)
        config = self.loop_config
        if not config.program:  # the boot program, compiled here (design.md §12)
            config = dataclasses.replace(config, compiled=self._boot_form())
        self.start_scan(config, timeout_s)
        if not stopping():
            self.start_services(timeout_s)
        record_semaphores(self.tag)

    def start_scan(self, config: LoopConfig, timeout_s: float = 30.0) -> None:
        ready = ReadySignal(self.ctx)
        self.scan = self.ctx.Process(
            target=self.scan_main, name="softplc-scan",
            args=(config, self.channel, self.shm_name, self.board_name, ready,
                  self.stop_scan, *self.scan_args))
        self.scan.start()
        self.boot_forms.started(config.compiled)
        self._scan_says = ready
        self.stop_scan.bind(self.scan.pid)
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.05) and not self._stopping():
            if not self.scan.is_alive():
                raise RuntimeError(f"the scan process exited ({self.scan.exitcode}) at start")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the scan process did not start within {timeout_s:g} s")

    def start_services(self, timeout_s: float = 30.0) -> None:
        """Every service process, started together (OPC UA takes seconds), then each waited
        for until it serves."""
        waiting = [(service, self._spawn(service)) for service in self.services]
        for service, ready in waiting:
            self._await_service(service, ready, timeout_s)

    def _spawn(self, service: ServiceProcess) -> ReadySignal:
        ready = ReadySignal(self.ctx)
        service.proc = self.ctx.Process(
            target=service.main, name=_TITLES[service.name][0],
            args=(service.config, self.channel, self.shm_name, self.board_name, ready,
                  service.stop))
        service.proc.start()
        service.stop.bind(service.proc.pid)
        keep_off_scan_cpu(service.proc.pid, self.loop_config.realtime)
        return ready

    def _await_service(self, service: ServiceProcess, ready: ReadySignal,
                       timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        # Stopping first: waiting first held a signal up 50 ms per service still starting,
        # before the safe write (measured: +70 ms with three service processes).
        while not self._stopping() and not ready.wait(0.05):
            if not service.proc.is_alive() or time.monotonic() > deadline:
                config = service.config
                host, port = getattr(config, "broker", None) or config.modbus or config.api \
                    or config.opcua or ("?", 0)
                raise RuntimeError(f"the {service.title} did not start (is {host}:{port} "
                                   "in use?)")

    def _budget(self, history: deque[float]) -> int:
        """Restarts within the window so far, after forgetting the older ones."""
        now = self.clock()
        while history and now - history[0] > RESTART_WINDOW_S:
            history.popleft()
        return len(history)

    def watch(self) -> list[str]:
        """Heal what died; return what happened (for the console). Raises GaveUp when the scan
        process died more than SCAN_RESTARTS times within RESTART_WINDOW_S."""
        said: list[str] = []
        if self._stopping():  # told to stop: a child ending now was told so too (a group's
            return said  # SIGTERM, systemd's KillMode=control-group), it is not restarted
        if self.scan is not None and not self.scan.is_alive() and not self.stop_scan.is_set():
            said += self._scan_died()
        if self._restart_due is not None and self.clock() >= self._restart_due:
            self._restart_due = None
            said.append(self._restart_scan())
        for service in self.services:
            proc = service.proc
            if proc is not None and not proc.is_alive() and not service.stop.is_set():
                said.append(self._service_died(service))
        return said

    def _scan_died(self) -> list[str]:
        code = self.scan.exitcode
        reason = (f"killed by signal {-code}" if code is not None and code < 0
                  else f"exited with code {code}")
        self.scan = None
        used = self._budget(self.scan_restarts)
        if used >= SCAN_RESTARTS:
            raise GaveUp(f"the scan process {reason}; it died {used + 1} times within "
                         f"{RESTART_WINDOW_S:g} s: giving up")
        paused, on_board = self._paused_when_died()
        if paused:
            reason += (" while paused at a breakpoint" if on_board
                       else " before it ran again after a pause at a breakpoint") + f" ({paused})"
        self.paused_at_restart = paused
        self.restart_reason = f"scan process {reason}"
        now = self.clock()
        recent = sum(1 for t in self.scan_restarts if now - t <= BACKOFF_WINDOW_S)
        delay = BACKOFF_S[min(recent, len(BACKOFF_S) - 1)]
        self._restart_due = now + delay
        return [f"scan process {reason}; restarting it warm"
                + (f" in {delay:g} s" if delay else "")
                + (": STOPPED, outputs safe, not run on (resume runs on)" if paused else "")]

    def _paused_when_died(self) -> tuple[str, bool]:
        """The pause the dead scan process last published on the board (its reason; a step
        running counts: a person is stepping the net), "" if it was running on; and whether
        the board said so. A board that says neither (another state, unreadable) keeps what
        the last restart knew: a PLC restarted STOPPED that dies again before it ran is not
        run on either."""
        doc = self.status()
        if doc.get("state") != "RUNNING":
            return self.paused_at_restart, False
        if pause := doc.get("paused"):
            return str(pause.get("reason") or "paused"), True
        if steps := doc.get("steps_left"):
            return f"a step running, {steps} scan(s) left", True
        return "", True

    def _restart_scan(self) -> str:
        self.scan_restarts.append(self.clock())
        self.restarts += 1
        # Event numbers go on: HTTP's Last-Event-ID and OPC UA's LastEventSeq hold across it
        self.event_seq = max(self.event_seq, newest_seq(self.status()))
        compiled = self._boot_form() if self.loop_config.state_dir else self.loop_config.compiled
        config = dataclasses.replace(
            self.loop_config, compiled=compiled, restarts=self.restarts,
            restart_reason=self.restart_reason, paused_at_restart=self.paused_at_restart,
            first_event_seq=self.event_seq,
            # The boot program (the last one accepted) and the newest snapshot: warm.
            program=None if self.loop_config.state_dir else self.loop_config.program,
            start=True)
        try:
            self.start_scan(config)
        except RuntimeError as exc:
            self.scan = None
            return f"restart {self.restarts} failed: {exc}"
        record_semaphores(self.tag)
        return f"scan process restarted (restart {self.restarts}, pid {self.scan.pid})"

    def _boot_form(self) -> Any:
        """The state directory's boot program (the last one accepted) compiled here while a
        scan process starts with it, and kept for the next restart: no scan process parses
        YAML."""
        self.loop_config, compiled = self.boot_forms.for_scan(self.loop_config)
        return compiled

    def _service_died(self, service: ServiceProcess) -> str:
        code = service.proc.exitcode
        used = self._budget(service.restarts)
        if used >= COMM_RESTARTS:
            service.proc = None
            return (f"{service.title} exited ({code}) {used + 1} times within "
                    f"{RESTART_WINDOW_S:g} s: it stays off; the PLC scans on")
        service.restarts.append(self.clock())
        try:
            self._await_service(service, self._spawn(service), 30.0)
        except RuntimeError as exc:
            return f"{service.title} exited ({code}); restart failed: {exc}"
        record_semaphores(self.tag)
        return f"{service.title} exited ({code}); restarted"

    def stop(self, timeout_s: float = STOP_S) -> None:
        """The scan process first: it drives outputs safe and has the devices confirm it, then
        says "safe"; only then every service process at once, so clients see the PLC until
        its outputs are safe (and their teardown takes no CPU from the safe write). Whatever
        still runs after `timeout_s` is killed."""
        deadline = time.monotonic() + timeout_s
        self.stop_scan.set()
        self.boot_forms.cancel()
        self._await_safe(min(deadline, time.monotonic() + SAFE_WAIT_S))
        for service in self.services:
            service.stop.set()
        services = [service.proc for service in self.services]
        for proc in (self.scan, *services):
            if proc is not None:
                proc.join(max(0.0, deadline - time.monotonic()))
        for proc in (*services, self.scan):
            if proc is not None and proc.is_alive():
                proc.kill()
                proc.join(1.0)
        self.final = self.status()  # what the scan process published last, safe outputs included
        if self.board is not None:
            self.board.close()
            self.board = None
        if self.segment is not None:
            self.segment.close()
            self.segment.unlink()
            self.segment = None
        with contextlib.suppress(OSError):
            Path(f"/dev/shm/{self.tag}_sems").unlink()

    def _await_safe(self, until: float) -> None:
        """Until the scan process said "safe", ended, or `until` (a scan main that says
        nothing, the benchmark's, ends after its safe write)."""
        says = self._scan_says
        while says is not None and self.scan is not None and self.scan.is_alive():
            left = until - time.monotonic()
            if left <= 0 or says.heard(ReadySignal.SAFE, min(left, 0.02)):
                return

    def status(self) -> dict[str, Any]:
        if self.board is None:
            return {}
        try:
            return self.board.read()
        except TimeoutError:
            return {}
