"""`softplc run`: start the scan process and the communication process, watch them, show a
live status line, and stop both on Ctrl-C or SIGTERM with outputs driven safe first.

Owns: process start order, shared-memory names, restarts of a crashed communication process,
the live status line, the banner (with the cold/warm start and its reason), refusing a state
directory another runtime holds. Does not know: what a scan does, what a snapshot holds.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from softplc.core.image import ImageSizes
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.runtime.board import StatusBoard
from softplc.runtime.channel import Channel, pid_alive
from softplc.runtime.comm import CommConfig, comm_process_main
from softplc.runtime.loop import LoopConfig, scan_process_main
from softplc.runtime.realtime import Realtime, keep_off_scan_cpu
from softplc.runtime.retain import StateDirBusy, check_state_dir

SHM_PREFIX = "softplc_"
COMM_RESTARTS = 5


def _remove_stale_segments() -> None:
    """Segments of runs that were killed (their pid is gone) are removed before we start."""
    shm_dir = Path("/dev/shm")
    if not shm_dir.is_dir():
        return
    for entry in shm_dir.glob(SHM_PREFIX + "*"):
        parts = entry.name.split("_")
        if len(parts) >= 2 and parts[1].isdigit() and not pid_alive(int(parts[1])):
            entry.unlink(missing_ok=True)


def die_with_parent() -> None:
    """In a child process: end when the supervisor ends, even if it was killed (SIGKILL).
    Linux delivers SIGTERM on the parent's death (PR_SET_PDEATHSIG); the loops also poll."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


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
                 scan_args: tuple[Any, ...] = (), tag: str | None = None) -> None:
        self.ctx = mp.get_context("spawn")
        self.channel = Channel(ctx=self.ctx)
        tag = tag or f"{SHM_PREFIX}{os.getpid()}"
        self.shm_name, self.board_name = f"{tag}_image", f"{tag}_board"
        self.stop_scan = self.ctx.Event()
        self.stop_comm = self.ctx.Event()
        self.loop_config, self.comm_config = loop_config, comm_config
        self.scan_main, self.scan_args = scan_main, scan_args
        self.scan: Any = None
        self.comm: Any = None
        self.comm_restarts = 0

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Supervisor:
        """`softplc run`'s flags. Raises ValueError for --rt-priority / --scan-cpu."""
        sizes = ImageSizes()
        root = Path(args.program).resolve().parent.parent if args.program else Path.cwd()
        loop_config = LoopConfig(
            program=args.program, start=args.start, period_ns=args.period, plant=args.plant,
            seed=args.seed, trace=args.trace, watchdog=args.watchdog, root=str(root),
            sizes=sizes, state_dir=args.state_dir,
            retain_interval_ns=getattr(args, "retain_interval", 1_000_000_000),
            warm_start=getattr(args, "warm_start", "run"),
            realtime=Realtime(getattr(args, "rt_priority", None), getattr(args, "scan_cpu", None)))
        comm_config = CommConfig(modbus=args.modbus, api=args.api, state_dir=args.state_dir,
                                 sizes=sizes, modbus_writes=getattr(args, "modbus_writes", "open"),
                                 opcua=getattr(args, "opcua", None))
        return cls(loop_config, comm_config)

    def start(self, timeout_s: float = 30.0) -> None:
        ready = self.ctx.Event()
        self.scan = self.ctx.Process(
            target=self.scan_main, name="softplc-scan",
            args=(self.loop_config, self.channel, self.shm_name, self.board_name, ready,
                  self.stop_scan, *self.scan_args))
        self.scan.start()
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.1):
            if not self.scan.is_alive():
                raise RuntimeError(f"the scan process exited ({self.scan.exitcode}) at start")
            if time.monotonic() > deadline:
                raise RuntimeError(f"the scan process did not start within {timeout_s:g} s")
        self.start_comm(timeout_s)

    def start_comm(self, timeout_s: float = 30.0) -> None:
        if (self.comm_config.modbus is None and self.comm_config.api is None
                and self.comm_config.opcua is None):
            return
        ready = self.ctx.Event()
        self.comm = self.ctx.Process(
            target=comm_process_main, name="softplc-comm",
            args=(self.comm_config, self.channel, self.shm_name, self.board_name, ready,
                  self.stop_comm))
        self.comm.start()
        keep_off_scan_cpu(self.comm.pid, self.loop_config.realtime)
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.1):
            if not self.comm.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the communication process did not start (is a port in use? "
                                   f"Modbus {self.comm_config.modbus}, API {self.comm_config.api})")

    def watch(self) -> None:
        """Restart a crashed communication process; the scan goes on regardless."""
        if self.comm is not None and not self.comm.is_alive() and not self.stop_comm.is_set():
            self.comm_restarts += 1
            print(f"\nsoftplc: communication process exited ({self.comm.exitcode}); "
                  f"restart {self.comm_restarts}/{COMM_RESTARTS}", file=sys.stderr)
            if self.comm_restarts <= COMM_RESTARTS:
                self.start_comm()
            else:
                self.comm = None

    def stop(self) -> None:
        self.stop_comm.set()
        if self.comm is not None:
            self.comm.join(10)
            if self.comm.is_alive():
                self.comm.terminate()
        self.stop_scan.set()  # the scan process drives outputs safe before it exits
        if self.scan is not None:
            self.scan.join(10)
            if self.scan.is_alive():
                self.scan.terminate()


def run(args: argparse.Namespace) -> int:
    if args.program:
        try:
            compile_file(args.program)
        except ProgramError as exc:
            for problem in exc.problems:
                print(problem, file=sys.stderr)
            return 1
    try:
        check_state_dir(args.state_dir)  # the scan process takes the lock; fail early and clearly
    except StateDirBusy as exc:
        print(f"softplc: {exc}", file=sys.stderr)
        return 1
    _remove_stale_segments()
    try:
        supervisor = Supervisor.from_args(args)
    except ValueError as exc:  # --rt-priority or --scan-cpu out of range
        print(f"softplc: {exc}", file=sys.stderr)
        return 2
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
        return 1
    board = StatusBoard.attach(supervisor.board_name)
    _banner(args, board.read())
    print(f"  scan process pid {supervisor.scan.pid} ({board.read().get('realtime', '?')}), "
          f"communication process pid {supervisor.comm.pid if supervisor.comm else '-'}",
          flush=True)
    began = time.monotonic()
    tty = sys.stdout.isatty() and not args.quiet
    last_print = 0.0
    try:
        while not stopping and supervisor.scan.is_alive():
            time.sleep(0.2)
            supervisor.watch()
            now = time.monotonic()
            if args.duration and now - began >= args.duration / 1e9:
                break
            if tty:
                print("\r" + status_line(board.read())[:150].ljust(150), end="", flush=True)
            elif not args.quiet and now - last_print >= 5:
                print(status_line(board.read()), flush=True)
                last_print = now
    finally:
        final = board.read()
        board.close()
        supervisor.stop()
    print(("\n" if tty else "") + "stopped: " + status_line(final) + ", outputs safe")
    return 0


def _banner(args: argparse.Namespace, doc: dict[str, Any]) -> None:
    print(f"softplc running {args.program or '(no program)'}"
          f" (period {args.period / 1e6:g} ms){' started' if args.start else ''}")
    print(f"  {doc.get('start_mode', '?')} start: {doc.get('start_reason', '?')}")
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
