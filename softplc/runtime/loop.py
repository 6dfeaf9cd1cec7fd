"""The real-time scan loop: the scan process of DESIGN.md section 7.

Owns: absolute deadlines on the monotonic clock, skipped slots counted as overruns, the
watchdog (execution time over period x sensitivity -> FAULTED, safe outputs), commands and
HMI writes drained at the scan boundary (downloads compiled off the scan by downloads.py and
applied at the first boundary after, so a bad program never reaches the PLC), the snapshot
published to shared memory after every scan,
retain captures at scan boundaries (written by retain.py's thread), the cold or warm start,
and safe outputs on shutdown.
Does not know: Modbus, HTTP (the communication process), terminals (the CLI).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from multiprocessing.synchronize import Event
from pathlib import Path
from typing import Any

from softplc.core.image import ImageSizes
from softplc.core.lifecycle import Command, PlcState
from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.core.scan import FAULT_WATCHDOG, Plc, ProgramCommand
from softplc.core.snapshot import CommandReply, CommandRequest, Status
from softplc.devices.driver import SAFE_TIMEOUT_S, go_safe_all
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime.board import StatusBoard
from softplc.runtime.channel import Channel
from softplc.runtime.clock import Clock, MonotonicClock, Schedule
from softplc.runtime.downloads import DownloadQueue
from softplc.runtime.realtime import NORMAL, Realtime, apply
from softplc.runtime.retain import (
    ContinuedClock,
    Loaded,
    RetainStore,
    RetainWriter,
    StartDecision,
    StateDirBusy,
    capture,
    decide,
    load_plant,
    restore,
)
from softplc.runtime.runner import ScanRunner, open_drivers
from softplc.runtime.shm import SnapshotWriter
from softplc.runtime.stats import TimingStats
from softplc.runtime.trace import TraceWriter


@dataclass(frozen=True, slots=True)
class LoopConfig:
    program: str | None = None  # compiled and downloaded on the first scan
    start: bool = False
    period_ns: int = 10_000_000
    plant: str | None = None  # overrides the plant of a sim driver
    seed: int = 0
    trace: str | None = None
    watchdog: float = 10.0  # fault when one scan runs longer than period x this
    root: str | None = None  # downloads may only reference files under this directory
    sizes: ImageSizes = ImageSizes()
    max_scans: int | None = None  # stop after this many (tests, benchmarks)
    state_dir: str | None = None  # retain snapshots live here; None: no retain, always cold
    retain_interval_ns: int = 1_000_000_000  # 0: only on stop
    warm_start: str = "run"  # a warm restart of a RUNNING snapshot: "run" resumes, "stop" waits
    realtime: Realtime = NORMAL  # SCHED_FIFO priority and CPU of the scan process


class ScanLoop:
    """One PLC on a clock. `run()` until `stop` is set (or max_scans)."""

    def __init__(self, config: LoopConfig, channel: Channel | None, writer: SnapshotWriter | None,
                 clock: Clock | None = None, board: StatusBoard | None = None) -> None:
        self.config = config
        self.channel = channel
        self.writer = writer
        self.board = board
        self.board_every = max(1, 50_000_000 // config.period_ns)  # about every 50 ms
        self.events: deque[dict[str, Any]] = deque(maxlen=256)
        self.event_seq = 0
        self.start_mode = "cold"
        self.start_reason = "retain off (no state directory)"
        self.realtime = "normal scheduling"  # what scan_process_main obtained
        self.clock: Clock = clock or MonotonicClock()
        self.stats = TimingStats()
        self.summary = self.stats.summary()  # refreshed every board_every scans, not every scan
        self.runner = ScanRunner(Plc.empty(), [], TraceWriter(config.trace) if config.trace else None)
        self.pending: list[ProgramCommand] = []
        self.downloads = DownloadQueue(self._compile)
        self._driver_specs: tuple[object, ...] = ()
        self.retain: RetainWriter | None = None
        self._retained_ns = 0
        net = compile_file(config.program) if config.program else None  # the CLI reports errors
        decision = StartDecision("cold", self.start_reason)
        if config.state_dir is not None:
            store = RetainStore.open(config.state_dir)  # StateDirBusy: another runtime has it
            decision = decide(store, net)
            self.retain = RetainWriter(store)
        self.start_mode, self.start_reason = decision.mode, decision.reason
        if net is not None and decision.snapshot is not None:
            self._warm(net, decision.snapshot)
        elif net is not None:
            self._cold(net)

    # -- retain -----------------------------------------------------------------------------

    def _cold(self, net: CompiledNet) -> None:
        """Download `net` (and start it, if asked) on the first scan, from its initial marking."""
        self.pending = [ProgramCommand(Command.DOWNLOAD, net, id=0)]
        if self.config.start:
            self.pending.append(ProgramCommand(Command.START, id=0))

    def _warm(self, net: CompiledNet, snap: Loaded) -> None:
        """Download `net`, open its devices and put the snapshot in; on a snapshot that does
        not fit after all (same hash, unusable content) fall back to a cold start."""
        payload = snap.payload
        resume = self.config.start and self.config.warm_start == "run"
        plc = self.runner.plc
        plc.apply(ProgramCommand(Command.DOWNLOAD, net), payload["now_ns"])
        try:
            state = restore(plc, payload, resume)
            plants = {name: load_plant(blob)
                      for name, blob in payload.get("field_simulation_only", {}).items()}
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, EOFError) as exc:
            self.runner.plc = Plc.empty(self.runner.plc.image)
            self._cold(net)
            self.start_mode = "cold"
            self.start_reason = f"snapshot {snap.path.name} unusable ({type(exc).__name__}: {exc})"
            return
        self._after(())  # the program's devices, opened before the first scan
        for driver in self.runner.drivers:
            if driver.name in plants and hasattr(driver, "plant"):
                driver.plant = plants[driver.name]  # simulation only: the field side
        self.clock = ContinuedClock(self.clock, payload["now_ns"])
        self._retained_ns = payload["now_ns"]
        self.start_reason += f" -> {state.name}"

    def _sim_plants(self) -> dict[str, object]:
        return {d.name: d.plant for d in self.runner.drivers if hasattr(d, "plant")}

    def _retain(self, now_ns: int, due: bool) -> None:
        """At a scan boundary: hand a consistent copy to the writer thread when due."""
        if self.retain is None or not due:
            return
        cap = capture(self.runner.plc, now_ns, self._sim_plants())
        if cap is not None:
            self.retain.submit(cap)
            self._retained_ns = now_ns

    # -- commands ---------------------------------------------------------------------------

    def _due_commands(self) -> list[ProgramCommand]:
        """The drained commands whose turn has come, in arrival order: downloads compiled
        (off the scan, runtime/downloads.py) or refused with every problem listed."""
        commands = []
        for item in self.downloads.take():
            req = item.request
            if req.command is not Command.DOWNLOAD:
                commands.append(ProgramCommand(req.command, online=req.online, id=req.id))
            elif isinstance(item.error, ProgramError):
                self._refuse(req, f"download refused:\n{item.error}")
            elif item.error is not None:  # a compiler bug must never stop the scan
                self._refuse(req, "download refused: internal compiler error "
                             f"({type(item.error).__name__}: {item.error})")
            elif item.net is not None and item.net.io.sizes != self.config.sizes:
                self._refuse(req, "download refused: the program's image sizes "
                             f"{item.net.io.sizes} differ from the runtime's")
            else:
                commands.append(ProgramCommand(Command.DOWNLOAD, item.net, req.online, req.id))
        return commands

    def _refuse(self, req: CommandRequest, message: str) -> None:
        self._reply(CommandReply(req.id, False, message, self.runner.plc.state))

    def _compile(self, req: CommandRequest):  # type: ignore[no-untyped-def]
        root = Path(self.config.root) if self.config.root else None
        name = req.program_path or "downloaded.yaml"
        if req.program_text is None:
            return compile_file(name, root)
        base = (root or Path.cwd()) / "programs"
        filename = str(base / Path(name).name) if not Path(name).is_absolute() else name
        return compile_text(req.program_text, filename, root)

    def _reply(self, reply: CommandReply) -> None:
        if reply.id == 0 or self.channel is None:
            return  # startup commands come from the command line, not from a client
        self.channel.reply(reply)

    def _after(self, replies: Sequence[CommandReply]) -> None:
        for reply in replies:
            self._reply(reply)
        net = self.runner.plc.net
        if net is not None and tuple(net.io.drivers.values()) != self._driver_specs:
            # Another io image (reconfiguration): its devices replace the old ones.
            self._driver_specs = tuple(net.io.drivers.values())
            self.runner.set_drivers(open_drivers(net.io, self.config.seed, self.config.plant))

    # -- the loop ---------------------------------------------------------------------------

    def scan_once(self, now_ns: int) -> bool:
        """One scan; True if it applied program commands (exempt from the watchdog: a
        download swaps the net and may open devices, not the program's execution time)."""
        requests, writes = self.channel.drain() if self.channel else ([], [])
        self.downloads.put(requests)
        commands = self.pending + self._due_commands()
        self.pending = []
        result = self.runner.step(now_ns, commands, writes)
        self._after(result.replies)
        for name in result.events:
            self.event_seq += 1
            self.events.append({"seq": self.event_seq, "scan": self.runner.plc.scan_count,
                                "t_ns": now_ns, "name": name})
        return bool(commands)

    def document(self) -> dict[str, Any]:
        """The status board: what `softplc status` and the HTTP API show."""
        plc = self.runner.plc
        timing: dict[str, Any] = dict(self.summary.as_dict())
        timing["p99_lateness_us"] = timing.get("lateness_p99_us", 0)
        timing["overruns"] = self.stats.overruns
        net = plc.net
        symbols = {} if net is None else {
            s.name: {"address": str(s.address), "type": s.type.value,
                     "direction": s.direction.value, "value": plc.image.get(s.address),
                     "hmi_writable": s.hmi_writable}
            for s in net.io.symbols.values()}
        return {
            "state": plc.state.name, "program": net.name if net else None,
            "program_hash": net.program_hash if net else None, "scan_count": plc.scan_count,
            "period_us": self.config.period_ns // 1000, "marking": plc.marking(),
            "timing": timing, "fault_code": plc.fault_code,
            "fault_reason": plc.fault_reason, "devices": self.runner.device_report(),
            "start_mode": self.start_mode,
            "start_reason": self.start_reason, "realtime": self.realtime,
            "retain": self.retain.info() if self.retain else None,
            "health": {name: h.value for name, h in self.runner.health().items()},
            "diagnostics": list(plc.engine.diagnostics[-20:]) if plc.engine else [],
            "symbols": symbols, "events": list(self.events),
        }

    def status(self) -> Status:
        plc = self.runner.plc
        return Status(plc.state, plc.scan_count, self.stats.last_exec_ns // 1000,
                      self.stats.max_exec_ns // 1000, int(self.summary.lateness_p99_us),
                      self.stats.overruns,
                      plc.net.program_hash if plc.net else "", plc.fault_code,
                      self.config.period_ns // 1000)

    def run(self, stop: Event | None = None) -> None:
        period = self.config.period_ns
        schedule = Schedule(self.clock, period)
        while (stop is None or not stop.is_set()) and (
                self.config.max_scans is None or self.runner.plc.scan_count < self.config.max_scans):
            deadline = schedule.deadline_ns
            reached = schedule.wait()
            handled_commands = self.scan_once(reached)
            done = self.clock.now_ns()
            exec_ns = done - reached
            if (exec_ns > period * self.config.watchdog and not handled_commands
                    and self.runner.plc.state is PlcState.RUNNING):
                self._watchdog()
            self.stats.record(exec_ns, reached - deadline, skipped=schedule.advance(done))
            refresh = self.runner.plc.scan_count % self.board_every == 0
            if refresh:  # percentiles cost ~20 µs: not on every scan
                self.summary = self.stats.summary()
            if self.writer is not None:
                self.writer.publish(self.runner.plc.image, self.status())
            interval = self.config.retain_interval_ns
            self._retain(reached, interval > 0 and reached - self._retained_ns >= interval)
            if self.board is not None and refresh:
                self.board.publish(self.document())
        self.shutdown()

    def _watchdog(self) -> None:
        plc = self.runner.plc
        plc.fault(FAULT_WATCHDOG)
        go_safe_all(self.runner.drivers, plc.image, SAFE_TIMEOUT_S)  # now, confirmed

    def shutdown(self) -> None:
        """Outputs to their safe values, written through the drivers, then close."""
        self.summary = self.stats.summary()
        plc = self.runner.plc
        # Retained before the outputs go safe: a warm restart resumes what the program drove.
        self._retain(self.clock.now_ns(), True)
        plc.drive_safe()
        go_safe_all(self.runner.drivers, plc.image, SAFE_TIMEOUT_S)  # written and confirmed
        if self.writer is not None:
            self.writer.publish(plc.image, self.status())
        if self.board is not None:
            self.board.publish(self.document())
        self.runner.close()
        self.downloads.close()
        if self.retain is not None:
            self.retain.close()  # waits for the last snapshot to be on disk


def _once(action: Callable[[], object]) -> Callable[[int, object], None]:
    """A SIGTERM handler that acts on the first signal only. A dying supervisor can deliver
    SIGTERM more than once (PR_SET_PDEATHSIG fires as each of its threads exits), and one
    arriving inside stop.set() re-entered it and deadlocked on its lock, outputs still on."""
    done: dict[str, bool] = {}

    def handler(signum: int, frame: object) -> None:
        if not done:
            done["yes"] = True  # no call before this store: no other handler can run first
            action()

    return handler


def scan_process_main(config: LoopConfig, channel: Channel, shm_name: str, board_name: str,
                      ready: Event, stop: Event) -> None:
    """Entry point of the scan process. SIGINT is the parent's business: it sets `stop`."""
    from softplc.runtime.supervisor import die_with_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _once(stop.set))
    die_with_parent()
    parent = os.getppid()

    def watch_parent() -> None:
        while not stop.wait(0.5):
            if os.getppid() != parent:
                stop.set()

    threading.Thread(target=watch_parent, name="watch-parent", daemon=True).start()
    realtime = apply(config.realtime)  # after the watcher: it keeps normal scheduling
    writer = SnapshotWriter.create(config.sizes, name=shm_name)
    board = StatusBoard.create(board_name)
    try:
        try:
            loop = ScanLoop(config, channel, writer, board=board)
            loop.realtime = realtime
        except StateDirBusy as exc:
            print(f"softplc: {exc}", file=sys.stderr)
            raise SystemExit(3) from None
        writer.publish(loop.runner.plc.image, loop.status())
        board.publish(loop.document())
        ready.set()
        loop.run(stop)
    finally:
        writer.close()
        writer.unlink()
        board.close()
