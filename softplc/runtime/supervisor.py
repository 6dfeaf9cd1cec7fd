"""`softplc run`: start the scan process and the communication process, watch them, heal
them, show a live status line, and stop both on Ctrl-C or SIGTERM with outputs driven safe.

Owns: process start order; the shared-memory segments (they outlive a scan process, so the
communication side keeps serving across a restart); restarting a dead scan process warm from
the newest retain snapshot and the boot program, with backoff, at most SCAN_RESTARTS times in
RESTART_WINDOW_S, then giving up with an exit code; restarting a dead communication process
within the same kind of budget; stopping everything within STOP_S on SIGTERM/SIGINT in every
state; removing what killed runs left in /dev/shm; the banner and the live status line.
Does not know: what a scan does, what a snapshot holds.

Exit codes (docs/operations.md): 0 stopped on request (SIGTERM, SIGINT, --duration); 1 could
not start (program, port, state directory); 2 bad command line; 3 gave up: the scan process
died more than SCAN_RESTARTS times within RESTART_WINDOW_S.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import gc
import multiprocessing as mp
import multiprocessing.synchronize as mp_sync
import os
import signal
import socket
import sys
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final

from softplc.core.image import ImageSizes
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.runtime.board import StatusBoard
from softplc.runtime.channel import Channel, pid_alive
from softplc.runtime.comm import CommConfig, comm_process_main, modbus_limits
from softplc.runtime.config import LoopConfig
from softplc.runtime.loop import scan_process_main
from softplc.runtime.procs import ReadySignal, StopFlag
from softplc.runtime.realtime import Realtime, keep_off_scan_cpu
from softplc.runtime.retain import StateDirBusy, check_state_dir
from softplc.runtime.runner import plant_conflict
from softplc.runtime.sdnotify import Notifier
from softplc.runtime.shm import SnapshotWriter

SHM_PREFIX: Final = "softplc_"
SCAN_RESTARTS: Final = 5  # scan process restarts allowed within RESTART_WINDOW_S
COMM_RESTARTS: Final = 5  # communication process restarts allowed within RESTART_WINDOW_S
RESTART_WINDOW_S: Final = 60.0
BACKOFF_S: Final = (0.0, 0.5, 1.0, 2.0, 4.0)  # by restarts within BACKOFF_WINDOW_S
BACKOFF_WINDOW_S: Final = 10.0  # a scan process that ran this long restarts without delay
STOP_S: Final = 2.0  # SIGTERM/SIGINT: every process gone within this (then SIGKILL)
EXIT_OK, EXIT_START, EXIT_USAGE, EXIT_GAVE_UP = 0, 1, 2, 3


class GaveUp(RuntimeError):
    """The scan process died too often: the supervisor stops instead of looping."""


def _remove_stale_segments() -> None:
    """Segments and named semaphores of runs that were killed (their pid is gone) are removed
    before we start: a kill -9 of the whole process group leaves both behind."""
    shm_dir = Path("/dev/shm")
    if not shm_dir.is_dir():
        return
    for entry in shm_dir.glob(SHM_PREFIX + "*"):
        parts = entry.name.split("_")
        if len(parts) < 2 or not parts[1].isdigit() or pid_alive(int(parts[1])):
            continue
        if entry.name.endswith("_sems"):
            for name in entry.read_text(encoding="utf-8", errors="replace").split():
                with contextlib.suppress(OSError):
                    (shm_dir / f"sem.{name.lstrip('/')}").unlink()
        entry.unlink(missing_ok=True)


def _record_semaphores(tag: str) -> None:
    """List this process's named semaphores (multiprocessing's Events, locks) where the next
    start finds them if this run is killed before its resource tracker can unlink them."""
    locks = [getattr(o, "_semlock", None) for o in gc.get_objects()
             if isinstance(o, mp_sync.SemLock)]
    names = sorted({str(lock.name) for lock in locks  # no name: unlinked at creation
                    if lock is not None and getattr(lock, "name", None)})
    with contextlib.suppress(OSError):
        Path(f"/dev/shm/{tag}_sems").write_text("\n".join(names), encoding="utf-8")


def status_line(doc: dict[str, Any]) -> str:
    timing = doc.get("timing", {})
    marked = ",".join(sorted(doc.get("marking", {}))) or "-"
    return (f"{doc.get('state', '?'):8} scans={doc.get('scan_count', 0):<8} "
            f"period={doc.get('period_us', 0) / 1000:g}ms "
            f"p99_late={timing.get('p99_lateness_us', 0):.0f}us "
            f"overruns={timing.get('overruns', 0)} marked={marked}")


class Supervisor:
    """The scan process and the communication process of one PLC. `scan_main` and its
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
        self.stop_comm = StopFlag()
        self.loop_config, self.comm_config = loop_config, comm_config
        self.scan_main, self.scan_args = scan_main, scan_args
        self.scan: Any = None
        self.comm: Any = None
        self.clock = clock
        self.scan_restarts: deque[float] = deque()  # when, within the window
        self.comm_restarts: deque[float] = deque()
        self.restarts = 0  # scan process restarts in this run, for status
        self.restart_reason = ""
        self._restart_due: float | None = None
        self.final: dict[str, Any] = {}
        self.segment: SnapshotWriter | None = None
        self.board: StatusBoard | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Supervisor:
        """`softplc run`'s flags. Raises ValueError for --rt-priority / --scan-cpu."""
        sizes = ImageSizes()
        root = Path(args.program).resolve().parent.parent if args.program else Path.cwd()
        loop_config = LoopConfig(
            program=args.program, start=args.start, period_ns=args.period, plant=args.plant,
            seed=args.seed, trace=args.trace, watchdog=args.watchdog, root=str(root),
            programs_dir=getattr(args, "programs_dir", None),
            sizes=sizes, state_dir=args.state_dir,
            retain_interval_ns=getattr(args, "retain_interval", 1_000_000_000),
            warm_start=getattr(args, "warm_start", "run"),
            on_stall=getattr(args, "on_stall", "fault"), verify=getattr(args, "verify", "warn"),
            stall_fault_ns=getattr(args, "stall_fault_after", 500_000_000),
            realtime=Realtime(getattr(args, "rt_priority", None), getattr(args, "scan_cpu", None)))
        comm_config = CommConfig(modbus=args.modbus, api=args.api, state_dir=args.state_dir,
                                 sizes=sizes, modbus_writes=getattr(args, "modbus_writes", "open"),
                                 opcua=getattr(args, "opcua", None), **modbus_limits(args))
        return cls(loop_config, comm_config)

    def start(self, timeout_s: float = 30.0) -> None:
        # The segments belong to the supervisor: they outlive a scan process, so the
        # communication process keeps its mapping (and says "stale") across a restart.
        self.segment = SnapshotWriter.create(self.loop_config.sizes, self.shm_name)
        self.board = StatusBoard.create(self.board_name)
        self.start_scan(self.loop_config, timeout_s)
        self.start_comm(timeout_s)
        _record_semaphores(self.tag)

    def start_scan(self, config: LoopConfig, timeout_s: float = 30.0) -> None:
        ready = ReadySignal(self.ctx)
        self.scan = self.ctx.Process(
            target=self.scan_main, name="softplc-scan",
            args=(config, self.channel, self.shm_name, self.board_name, ready,
                  self.stop_scan, *self.scan_args))
        self.scan.start()
        self.stop_scan.bind(self.scan.pid)
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.05):
            if not self.scan.is_alive():
                raise RuntimeError(f"the scan process exited ({self.scan.exitcode}) at start")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the scan process did not start within {timeout_s:g} s")

    def start_comm(self, timeout_s: float = 30.0) -> None:
        if (self.comm_config.modbus is None and self.comm_config.api is None
                and self.comm_config.opcua is None):
            return
        ready = ReadySignal(self.ctx)
        self.comm = self.ctx.Process(
            target=comm_process_main, name="softplc-comm",
            args=(self.comm_config, self.channel, self.shm_name, self.board_name, ready,
                  self.stop_comm))
        self.comm.start()
        self.stop_comm.bind(self.comm.pid)
        keep_off_scan_cpu(self.comm.pid, self.loop_config.realtime)
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.05):
            if not self.comm.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the communication process did not start (is a port in use? "
                                   f"Modbus {self.comm_config.modbus}, API {self.comm_config.api})")

    def _budget(self, history: deque[float]) -> int:
        """Restarts within the window so far, after forgetting the older ones."""
        now = self.clock()
        while history and now - history[0] > RESTART_WINDOW_S:
            history.popleft()
        return len(history)

    def watch(self) -> list[str]:
        """Heal what died; return what happened (for the console). Raises GaveUp when the scan
        process died more than SCAN_RESTARTS times within RESTART_WINDOW_S."""
        said = []
        if self.scan is not None and not self.scan.is_alive() and not self.stop_scan.is_set():
            said += self._scan_died()
        if self._restart_due is not None and self.clock() >= self._restart_due:
            self._restart_due = None
            said.append(self._restart_scan())
        if self.comm is not None and not self.comm.is_alive() and not self.stop_comm.is_set():
            said.append(self._comm_died())
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
        self.restart_reason = f"scan process {reason}"
        now = self.clock()
        recent = sum(1 for t in self.scan_restarts if now - t <= BACKOFF_WINDOW_S)
        delay = BACKOFF_S[min(recent, len(BACKOFF_S) - 1)]
        self._restart_due = now + delay
        return [f"scan process {reason}; restarting it warm"
                + (f" in {delay:g} s" if delay else "")]

    def _restart_scan(self) -> str:
        self.scan_restarts.append(self.clock())
        self.restarts += 1
        config = dataclasses.replace(
            self.loop_config, restarts=self.restarts, restart_reason=self.restart_reason,
            # The boot program (the last one accepted) and the newest snapshot: warm.
            program=None if self.loop_config.state_dir else self.loop_config.program,
            start=True)
        try:
            self.start_scan(config)
        except RuntimeError as exc:
            self.scan = None
            return f"restart {self.restarts} failed: {exc}"
        _record_semaphores(self.tag)
        return f"scan process restarted (restart {self.restarts}, pid {self.scan.pid})"

    def _comm_died(self) -> str:
        code = self.comm.exitcode
        used = self._budget(self.comm_restarts)
        if used >= COMM_RESTARTS:
            self.comm = None
            return (f"communication process exited ({code}) {used + 1} times within "
                    f"{RESTART_WINDOW_S:g} s: Modbus and API stay off; the PLC scans on")
        self.comm_restarts.append(self.clock())
        try:
            self.start_comm()
        except RuntimeError as exc:
            return f"communication process exited ({code}); restart failed: {exc}"
        _record_semaphores(self.tag)
        return f"communication process exited ({code}); restarted"

    def stop(self, timeout_s: float = STOP_S) -> None:
        """Both processes told at once; the scan drives outputs safe (confirmed by the devices)
        before it exits. Whatever still runs after `timeout_s` is killed."""
        self.stop_comm.set()
        self.stop_scan.set()  # the scan process drives outputs safe before it exits
        deadline = time.monotonic() + timeout_s
        for proc in (self.scan, self.comm):
            if proc is not None:
                proc.join(max(0.0, deadline - time.monotonic()))
        for proc in (self.comm, self.scan):
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

    def status(self) -> dict[str, Any]:
        if self.board is None:
            return {}
        try:
            return self.board.read()
        except TimeoutError:
            return {}


def _port_in_use(endpoint: tuple[str, int] | None) -> str | None:
    if endpoint is None or endpoint[1] == 0:
        return None
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(endpoint)
        except OSError as exc:
            return f"{endpoint[0]}:{endpoint[1]}: {exc.strerror}"
    return None


def _startup_problem(args: argparse.Namespace) -> str | None:
    """The first reason `softplc run` cannot start, as one line; None when it can."""
    if args.program:
        why = plant_conflict(compile_file(args.program).io, args.plant)
        if why:
            return why
    for what, endpoint in (("Modbus", args.modbus), ("API", args.api)):
        if problem := _port_in_use(endpoint):
            return f"{what} port {problem} (another softplc? choose another with --{what.lower()})"
    state = Path(args.state_dir)
    try:
        state.mkdir(parents=True, exist_ok=True)
        probe = state / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        return (f"state directory {state} is not usable: {exc.strerror} "
                "(choose one with --state-dir)")
    return None


def run(args: argparse.Namespace) -> int:
    if args.program:
        try:
            compile_file(args.program)
        except ProgramError as exc:
            for problem in exc.problems:
                print(problem, file=sys.stderr)
            return EXIT_START
    try:
        check_state_dir(args.state_dir)  # the scan process takes the lock; fail early and clearly
    except StateDirBusy as exc:
        print(f"softplc: {exc}", file=sys.stderr)
        return EXIT_START
    if trouble := _startup_problem(args):
        print(f"softplc: {trouble}", file=sys.stderr)
        return EXIT_START
    _remove_stale_segments()
    try:
        supervisor = Supervisor.from_args(args)
    except ValueError as exc:  # --rt-priority or --scan-cpu out of range
        print(f"softplc: {exc}", file=sys.stderr)
        return EXIT_USAGE
    stopping = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        supervisor.start()
    except RuntimeError as exc:
        print(f"softplc: {exc}", file=sys.stderr)
        supervisor.stop()
        return EXIT_START
    notifier = Notifier()
    notifier.send(f"READY=1\nMAINPID={os.getpid()}\nSTATUS=scanning")
    _banner(args, supervisor.status())
    print(f"  scan process pid {supervisor.scan.pid} ({supervisor.status().get('realtime', '?')}), "
          f"communication process pid {supervisor.comm.pid if supervisor.comm else '-'}",
          flush=True)
    print(f"  supervisor pid {os.getpid()}: SIGTERM or SIGINT stops everything within "
          f"{STOP_S:g} s; exit code 0 then, 3 if it gives up restarting", flush=True)
    return _supervise(supervisor, args, lambda: stopping, notifier)


def _supervise(supervisor: Supervisor, args: argparse.Namespace,
               stopping: Callable[[], bool], notifier: Notifier) -> int:
    began = time.monotonic()
    tty = sys.stdout.isatty() and not args.quiet
    last_print = 0.0
    code = EXIT_OK
    try:
        while not stopping():
            time.sleep(0.05)
            try:
                said = supervisor.watch()
            except GaveUp as exc:
                print(("\n" if tty else "") + f"softplc: {exc}", file=sys.stderr, flush=True)
                code = EXIT_GAVE_UP
                break
            for line in said:
                print(("\n" if tty else "") + f"softplc: {line}", file=sys.stderr, flush=True)
                notifier.send(f"STATUS={line}")
            now = time.monotonic()
            notifier.ping(now)
            if args.duration and now - began >= args.duration / 1e9:
                break
            if tty:
                print("\r" + status_line(supervisor.status())[:150].ljust(150), end="", flush=True)
            elif not args.quiet and now - last_print >= 5:
                print(status_line(supervisor.status()), flush=True)
                last_print = now
    finally:
        notifier.send("STOPPING=1")
        supervisor.stop()
        final = supervisor.final
    ending = "gave up" if code else "stopped"
    print(("\n" if tty else "") + f"{ending}: " + status_line(final) + ", outputs safe",
          flush=True)
    return code


def _banner(args: argparse.Namespace, doc: dict[str, Any]) -> None:
    print(f"softplc running {args.program or '(no program)'}"
          f" (period {args.period / 1e6:g} ms){' started' if args.start else ''}")
    print(f"  {doc.get('start_mode', '?')} start: {doc.get('start_reason', '?')}")
    print(f"  program: {doc.get('program_source', '?')}; restarts: scan process restarted "
          f"warm from the newest snapshot, at most {SCAN_RESTARTS} times in "
          f"{RESTART_WINDOW_S:g} s")
    interval = getattr(args, "retain_interval", 0)
    print(f"  retain in {args.state_dir}/: "
          + (f"every {interval / 1e9:g} s and on stop" if interval else "on stop only"))
    if args.modbus:
        host, port = args.modbus
        print(f"  Modbus TCP slave on {host}:{port}; try: "
              f"mbpoll -m tcp -p {port} -a 1 -0 -1 -t 0 -r 0 -c 8 {host}")
    if args.api:
        host, port = args.api
        print(f"  HTTP API on http://{host}:{port}; try: curl -s http://{host}:{port}/api/v1/status")
    if getattr(args, "opcua", None):
        host, port = args.opcua
        print(f"  OPC UA server on opc.tcp://{host}:{port} (writes and methods: user token)")
    print("  Ctrl-C stops (outputs to their safe values first)", flush=True)
