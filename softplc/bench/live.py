"""A live runtime for the benchmarks: the scan and communication processes of `softplc run`,
with every scan's lateness recorded, and the empty loop of the same scheduler (the floor).

Owns: RecordingStats (every scan's time, lateness, execution time and skipped slots in
preallocated arrays), RecordingLoop (a ScanLoop that also notes each net it loads), the
bench scan process (the production one plus a results pipe), the floor process, LiveRuntime
(start both processes as the supervisor does, stop them even on error) and free ports.
Does not know: what load is put on the runtime, or how figures are reported.
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.synchronize import Event
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
import numpy.typing as npt

from softplc.core.image import ImageSizes
from softplc.core.judge import NOTHING_OBSERVED, Observed
from softplc.runtime.clock import MonotonicClock, Schedule
from softplc.runtime.config import LoopConfig
from softplc.runtime.loop import ScanLoop
from softplc.runtime.realtime import NORMAL, Realtime, apply, share_interpreter
from softplc.runtime.scanproc import attached, scan_process_main
from softplc.runtime.serve.comm import CommConfig
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.procs import die_with_parent
from softplc.runtime.shared.shm import SnapshotWriter
from softplc.runtime.stats import TimingStats
from softplc.runtime.supervise.leftovers import SHM_PREFIX
from softplc.runtime.supervise.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[2]  # the checkout: programs/ and io_images/
TRANSPORT = ROOT / "programs" / "transport.yaml"
_CTX = mp.get_context("spawn")  # as the supervisor: no state inherited from the harness
_NAMES = itertools.count()
# The production watchdog (10 periods) faults the PLC when this shared, noisy machine
# preempts the scan process for 10 ms: a faulted PLC stops running its net, and the rest of
# the run would measure an idle loop. The benchmark counts such scans as overruns instead.
BENCH_WATCHDOG = 1000.0


def end_run(proc: Any) -> None:
    """End a `softplc run` started in its own session: SIGTERM, then its whole group killed
    after 10 s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)


def free_port() -> int:
    """A port on 127.0.0.1 that was free a moment ago (the comm process needs a number)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_kib(pid: int) -> int:
    """Resident memory of `pid` (VmRSS of /proc/PID/status), 0 if it is gone."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def cpu_s(pid: int) -> float:
    """User + system CPU seconds `pid` has used so far (/proc/PID/stat)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@dataclass(slots=True)
class ScanRecord:
    """Every recorded scan: when it was recorded (ns, monotonic, system-wide), its lateness
    and execution time (ns) and the slots it skipped; plus the nets loaded on the way."""

    at_ns: npt.NDArray[np.int64]
    late_ns: npt.NDArray[np.int64]
    exec_ns: npt.NDArray[np.int64]
    missed: npt.NDArray[np.int64]
    changes: list[dict[str, Any]] = field(default_factory=list)

    def window(self, t0_ns: int, t1_ns: int) -> ScanRecord:
        keep = (self.at_ns >= t0_ns) & (self.at_ns < t1_ns)
        return ScanRecord(self.at_ns[keep], self.late_ns[keep], self.exec_ns[keep],
                          self.missed[keep])

    def concat(self, other: ScanRecord) -> ScanRecord:
        return ScanRecord(np.concatenate((self.at_ns, other.at_ns)),
                          np.concatenate((self.late_ns, other.late_ns)),
                          np.concatenate((self.exec_ns, other.exec_ns)),
                          np.concatenate((self.missed, other.missed)))


class RecordingStats(TimingStats):
    """TimingStats that also keeps every scan, up to `capacity`, for histograms and windows."""

    __slots__ = ("_clock", "at_ns", "count", "exec_ns_all", "late_ns_all", "missed")

    def __init__(self, capacity: int, window: int = 1000) -> None:
        super().__init__(window)
        self._clock = MonotonicClock()
        self.at_ns = np.zeros(capacity, dtype=np.int64)
        self.late_ns_all = np.zeros(capacity, dtype=np.int64)
        self.exec_ns_all = np.zeros(capacity, dtype=np.int64)
        self.missed = np.zeros(capacity, dtype=np.int64)
        self.count = 0

    def record(self, exec_ns: int, lateness_ns: int, *, overrun: bool = False,
               skipped: int = 0) -> None:
        i = self.count
        if i < len(self.at_ns):
            self.at_ns[i] = self._clock.now_ns()
            self.late_ns_all[i] = lateness_ns
            self.exec_ns_all[i] = exec_ns
            self.missed[i] = max(skipped, 1 if overrun else 0)
            self.count = i + 1
        super().record(exec_ns, lateness_ns, overrun=overrun, skipped=skipped)

    def as_record(self, changes: list[dict[str, Any]]) -> ScanRecord:
        n = self.count
        return ScanRecord(self.at_ns[:n].copy(), self.late_ns_all[:n].copy(),
                          self.exec_ns_all[:n].copy(), self.missed[:n].copy(), changes)


class RecordingLoop(ScanLoop):
    """The production scan loop, recording every scan and each net it loads."""

    def __init__(self, config: LoopConfig, channel: Channel | None,
                 writer: SnapshotWriter | None, board: StatusBoard | None, capacity: int) -> None:
        super().__init__(config, channel, writer, board=board)
        self.stats: RecordingStats = RecordingStats(capacity)
        self.summary = self.stats.summary()
        self.changes: list[dict[str, Any]] = []

    def scan_once(self, now_ns: int, observed: Observed = NOTHING_OBSERVED) -> bool:
        before = self.runner.plc.net
        handled = super().scan_once(now_ns, observed)  # the loop passes what it observed
        net = self.runner.plc.net
        if net is not None and net is not before:
            # The first scan of the new net is this one: core.scan fires it after the download.
            self.changes.append({"index": self.stats.count, "reached_ns": now_ns,
                                 "done_ns": self.clock.now_ns(), "program_hash": net.program_hash,
                                 "transitions": len(net.transitions)})
        return handled


def bench_scan_main(config: LoopConfig, channel: Channel, shm_name: str, board_name: str,
                    ready: Event, stop: Event, results: Connection, capacity: int) -> None:
    """scan_process_main with a RecordingLoop; the record goes to `results` at the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    die_with_parent()
    realtime = apply(config.realtime) + ", " + share_interpreter(config.period_ns)
    # The supervisor created both segments (it owns them, as for `softplc run`): publish into
    # them. Creating them here replaced the supervisor's, which then leaked in the harness.
    with attached(config, shm_name, board_name) as (writer, board):
        loop = RecordingLoop(config, channel, writer, board, capacity)
        loop.realtime = realtime
        writer.publish(loop.runner.plc.image, loop.status())
        board.publish(loop.document())
        ready.set()
        loop.run(stop)
        results.send(loop.stats.as_record(loop.changes))


def floor_main(period_ns: int, duration_s: float, results: Connection,
               realtime: Realtime = NORMAL) -> None:
    """The floor: ScanLoop.run's deadline arithmetic on the same clock, with no scan at all,
    scheduled as the scan is."""
    die_with_parent()
    apply(realtime)
    clock = MonotonicClock(busy=realtime.busy_wait)
    stats = RecordingStats(int(duration_s * 1e9 / period_ns) + 16)
    schedule = Schedule(clock, period_ns)
    end = schedule.start_ns + int(duration_s * 1e9)
    while (deadline := schedule.deadline_ns) < end:
        reached = schedule.wait()
        done = clock.now_ns()
        stats.record(done - reached, reached - deadline, skipped=schedule.advance(done))
    results.send(stats.as_record([]))


def run_floor(period_ns: int, duration_s: float, realtime: Realtime = NORMAL) -> ScanRecord:
    """The floor loop in its own process, like the scan; its record."""
    receiver, sender = _CTX.Pipe(duplex=False)
    proc = _CTX.Process(target=floor_main, args=(period_ns, duration_s, sender, realtime),
                        name="softplc-bench-floor")
    proc.start()
    try:
        if not receiver.poll(duration_s + 60):
            raise RuntimeError("the floor process sent no record")
        record: ScanRecord = receiver.recv()
        return record
    finally:
        proc.join(5)
        if proc.is_alive():
            proc.kill()
            proc.join(5)


class LiveRuntime:
    """Scan process + communication process (Modbus slave and HTTP API on loopback), started
    as `softplc run` starts them. `record=True` runs the RecordingLoop (lateness of every
    scan, returned by stop()); `record=False` runs the production scan process unchanged."""

    def __init__(self, program: Path | None = TRANSPORT, *, period_ns: int = 1_000_000,
                 start: bool = True, plant: str | None = "transport", record: bool = True,
                 capacity_s: float = 120.0, api: bool = True, modbus: bool = True,
                 watchdog: float = BENCH_WATCHDOG, realtime: Realtime = NORMAL,
                 opcua: bool = False, keeps_state: bool = False) -> None:
        """`keeps_state`: the scan process keeps the boot program and retain in the state
        directory, as `softplc run` does by default (--state-dir state); off, only the
        communication process uses it (users, audit)."""
        sizes = ImageSizes()
        self.period_ns = period_ns
        self.record = record
        self._state_dir = tempfile.TemporaryDirectory(prefix="softplc-bench-")
        loop_config = LoopConfig(
            program=str(program) if program else None, start=start, period_ns=period_ns,
            plant=plant, root=str(ROOT), sizes=sizes, watchdog=watchdog, realtime=realtime,
            state_dir=self._state_dir.name if keeps_state else None)
        self.modbus_port = free_port() if modbus else None
        self.api_port = free_port() if api else None
        self.opcua_port = free_port() if opcua else None
        comm_config = CommConfig(
            modbus=("127.0.0.1", self.modbus_port) if self.modbus_port else None,
            api=("127.0.0.1", self.api_port) if self.api_port else None,
            state_dir=self._state_dir.name, sizes=sizes,
            opcua=("127.0.0.1", self.opcua_port) if self.opcua_port else None)
        self._receiver, sender = _CTX.Pipe(duplex=False)
        capacity = int(capacity_s * 1e9 / period_ns) + 1024
        self.supervisor = Supervisor(
            loop_config, comm_config, tag=f"{SHM_PREFIX}{os.getpid()}_bench{next(_NAMES)}",
            scan_main=bench_scan_main if record else scan_process_main,
            scan_args=(sender, capacity) if record else ())
        self.board: StatusBoard | None = None
        self._stopped = False
        self._record: ScanRecord | None = None

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    @property
    def channel(self) -> Channel:
        return self.supervisor.channel

    @property
    def scan(self) -> Any:
        return self.supervisor.scan

    @property
    def comm(self) -> Any:
        """The Modbus process (the one the Modbus figures are about)."""
        return self.supervisor.modbus

    def start(self, timeout_s: float = 60.0) -> None:
        """As `softplc run` starts: the scan process, then the communication process."""
        self.supervisor.start(timeout_s)
        self.board = StatusBoard.attach(self.supervisor.board_name)

    def status(self) -> dict[str, Any]:
        assert self.board is not None
        return self.board.read()

    def wait_for_state(self, state: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        seen = None
        while time.monotonic() < deadline:
            seen = self.status().get("state")
            if seen == state:
                return
            if not self.scan.is_alive():
                raise RuntimeError("the scan process died")
            time.sleep(0.05)
        raise RuntimeError(f"the PLC did not reach {state} within {timeout_s} s (it is {seen})")

    def stop(self) -> ScanRecord | None:
        """Stop both processes (comm first, as the supervisor does); the record, if any.
        Calling it again returns the same record."""
        if self._stopped:
            return self._record
        self._stopped = True
        record: ScanRecord | None = None
        for service in self.supervisor.services:
            service.stop.set()
        for service in self.supervisor.services:
            _end(service.proc)
        self.supervisor.stop_scan.set()
        if self.scan is not None and self.record and self._receiver.poll(30):
            record = self._receiver.recv()
        _end(self.scan)
        if self.board is not None:
            self.board.close()
            self.board = None
        # Both processes have ended: this closes and unlinks the segments the supervisor owns
        # (left open, they were garbage collected with numpy views still on them: BufferError
        # tracebacks, then the resource tracker's "leaked shared_memory objects" at exit).
        self.supervisor.stop()
        self._state_dir.cleanup()
        self._record = record
        return record

    def __enter__(self) -> LiveRuntime:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


def _end(proc: Any) -> None:
    if proc is None:
        return
    proc.join(15)
    if proc.is_alive():
        proc.kill()
        proc.join(5)
