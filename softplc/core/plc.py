"""The PLC's memory between scans and how commands change it.

Owns: Plc (state, image, program, engine, events, forcing, device watches) with program
handling per the lifecycle table (download, start, stop, resume, reset, kill), online change
with the marking carried over by place name, frozen timers while stopped, faults and device
recovery, HMI writes and safe outputs; ProgramCommand, a command as the scan applies it
(ScanContext, the guards' view of the image, is core/context.py's, imported here for scan.py).
The outputs kept while the program does not drive them, safe values and the devices a start
waits for are core/held.py's.
Does not know: the order of a scan (core/scan.py), clocks, processes, sockets, YAML.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from softplc.core import events as event_conditions
from softplc.core import memory, online, verdict
from softplc.core.breakpoints import Breakpoints
from softplc.core.context import ScanContext
from softplc.core.engine import Engine
from softplc.core.faults import DeviceMonitor
from softplc.core.forcing import Force, ForceRefused, Forces
from softplc.core.held import HeldOutputs, IoWait, awaited_devices, drive_safe
from softplc.core.image import Area, ProcessImage
from softplc.core.lifecycle import (
    Command,
    CommandRejected,
    PlcState,
    Stage,
    accepting,
    next_stage,
    stage_of,
)
from softplc.core.net import Busy, CompiledNet, NetState
from softplc.core.online import CarryPlan
from softplc.core.present import shown_rounded
from softplc.core.problems import FaultCode
from softplc.core.result import ScanResult
from softplc.core.snapshot import HmiWrite
from softplc.core.symbols import DriverSpec, FaultPolicy, SymType

# Kept for readers of older code and tests: the codes are FaultCode's.
FAULT_NONE, FAULT_WATCHDOG, FAULT_DEVICE = FaultCode.NONE, FaultCode.WATCHDOG, FaultCode.DEVICE
_PLAIN = (SymType.BOOL, SymType.WORD)  # read and written as their raw bits


@dataclass(frozen=True, slots=True)
class ProgramCommand:
    """A command as the scan sees it: a download carries an already compiled net."""

    command: Command
    net: CompiledNet | None = None
    online: bool = False
    id: int = 0
    symbol: str | None = None  # FORCE/UNFORCE: the symbol (UNFORCE None: release all)
    value: int = 0  # FORCE: the forced value's raw bits (core/present.py converts a typed one)
    replace: bool = False  # a download of another program while RUNNING: replace it
    # Built off the scan for `net` (runtime/loop.py): the engine's tables and the carry plan
    # against the running net, so that the swap costs a few array operations.
    engine: Engine | None = None
    plan: CarryPlan | None = None


@dataclass
class Plc:
    """Everything a PLC remembers between scans. Create with Plc.empty(); advance with scan()."""

    state: PlcState
    image: ProcessImage
    prev: ProcessImage
    net: CompiledNet | None = None
    engine: Engine | None = None
    events: event_conditions.EventMemory = field(default_factory=event_conditions.EventMemory)
    last_events: frozenset[str] = frozenset()  # emitted last scan: visible to guards now
    true_last: frozenset[str] = frozenset()  # every event true last scan: guards re-check
    held: HeldOutputs | None = None  # outputs at stop, restored on resume (core/held.py)
    written_last: set[str] = field(default_factory=set)
    scan_count: int = 0
    fault_code: FaultCode = FaultCode.NONE
    fault_reason: str = ""  # what faulted the PLC, for people (status, events)
    stopped_at_ns: int | None = None
    locations: dict[str, tuple[str, int]] = field(default_factory=dict)
    typed: dict[str, SymType] = field(default_factory=dict)  # beyond bool and word: decoded
    by_location: dict[tuple[str, int], tuple[str, ...]] = field(default_factory=dict)
    devices: DeviceMonitor = field(default_factory=DeviceMonitor)
    _policies_of: CompiledNet | None = None
    _policies: Mapping[str, FaultPolicy] = field(default_factory=dict)
    forces: Forces = field(default_factory=Forces)  # docs/design.md section 10
    debug: Breakpoints = field(default_factory=Breakpoints)  # breakpoints, pause (debug.md)
    # The device answers judged last with every device OK (core/judge.py: the steady scan), if so.
    steady_answers: Mapping[str, bool] | None = None
    context: ScanContext | None = None  # the guards' view of the image, kept between scans
    # The result of a scan in which nothing happened, shared by such scans (ScanResult is
    # immutable; its empty marking_changes is never written to).
    quiet_result: ScanResult | None = None
    # Start-up (docs/faults.md): the drivers the runtime has open (None: no device layer, the
    # caller's inputs are the image), the devices not delivered yet, a RUNNING PLC's wait for
    # them (since when, and the program's outputs: safe values go out meanwhile).
    open_devices: Mapping[str, DriverSpec | None] | None = None
    waiting_io: tuple[str, ...] = ()
    io_wait: IoWait | None = None
    first_round: bool = True  # the next firing round is the first since a start (first_scan)
    # Memory symbols that kept a value from another program at the last download (status).
    kept_across: memory.Kept | None = None
    _io_ready: tuple[object, object, object] | None = None  # awaited() found none for these

    @classmethod
    def empty(cls, image: ProcessImage | None = None) -> Plc:
        image = image or ProcessImage()
        return cls(PlcState.EMPTY, image, image.copy())

    def policies(self) -> Mapping[str, FaultPolicy]:
        """The device fault policies of the program's io image (computed once per program)."""
        if self._policies_of is not self.net:
            self._policies_of = self.net
            drivers = self.net.io.drivers if self.net is not None else {}
            self._policies = {name: spec.policy for name, spec in drivers.items()}
        return self._policies

    def marking(self) -> dict[str, int]:
        if self.net is None or self.engine is None:
            return {}
        return self.engine.state.marking_by_name(self.net)

    @property
    def stage(self) -> Stage:
        """The lifecycle's stage: a STOPPED PLC is SUSPENDED when a stop froze its marking
        and timers (`stopped_at_ns`, which retain keeps), READY when it holds the initial one."""
        return stage_of(self.state, self.stopped_at_ns is not None)

    # -- program handling -------------------------------------------------------------------

    def apply(self, cmd: ProgramCommand, now_ns: int) -> str:
        """Apply one command. Raises CommandRejected and changes nothing when refused."""
        if cmd.command is Command.FORCE or cmd.command is Command.UNFORCE:
            return self._force(cmd)
        target = next_stage(self.stage, cmd.command).state
        self.end_io_wait(now_ns)  # a command ends a wait as it stands; the scan re-decides
        if target is not PlcState.RUNNING:
            self.unpause(now_ns)  # stop, kill: the pause ends as a continue would end it
        if cmd.command is Command.DOWNLOAD:
            if cmd.net is None:
                raise CommandRejected(self.state, cmd.command, "download without a program")
            fate = verdict.decide(self.stage, self.net, self.engine.state if self.engine
                                  else None, cmd.net, online_change=cmd.online,
                                  replace=cmd.replace, plan=cmd.plan)  # as the dry run's
            if not fate.accepted:
                raise CommandRejected(self.state, cmd.command, fate.reason)
            if fate.plan is not None:  # an online change, its plan checked
                return self._online_change(cmd, fate.plan)
            if fate.outcome is verdict.Outcome.REPLACEMENT:
                return self._replace(cmd)
            self._load(cmd.net, self._fresh(cmd.net), cmd.engine, clear=True)
        elif cmd.command is Command.START or cmd.command is Command.RESET:
            assert self.net is not None
            self._load(self.net, self._fresh(self.net), clear=cmd.command is Command.RESET)
            if cmd.command is Command.RESET:  # a start keeps what was forced while READY
                self.forces.release(None)  # a reset drops every force (docs/design.md 10)
        elif cmd.command is Command.RESUME:
            self._thaw(now_ns)
            self.events.rearm()
        if target is PlcState.RUNNING:
            self.first_round = True
        if target is not PlcState.RUNNING and self.state is PlcState.RUNNING:
            self.stopped_at_ns = now_ns
            self.held = HeldOutputs.of(self.image)
        if cmd.command is Command.RESUME and self.held is not None:
            self.held.restore(self.image)
        if cmd.command is not Command.STOP:
            self.held = None
        self.state = target
        if target is not PlcState.FAULTED:
            self.fault_code, self.fault_reason = FAULT_NONE, ""
        kept = self.kept_across if cmd.command is Command.DOWNLOAD else None
        return f"{cmd.command.value}: now {target.name}" + (kept.note() if kept else "")

    def _fresh(self, net: CompiledNet) -> NetState:
        """`net`'s initial state, persistent places kept from a program of the same name."""
        return NetState.fresh(net, self.net, self.engine.state if self.engine else None)

    def _load(self, net: CompiledNet, state: NetState, engine: Engine | None = None,
              clear: bool = False) -> None:
        """`net` with `state` in; memory symbols new to the image take their `init:`, and with
        `clear` (download, reset) the non-retained ones too (core/memory.py)."""
        before = self.net.io if self.net is not None else None
        if net.io.sizes != self.image.sizes:
            self.image, self.prev = ProcessImage(net.io.sizes), ProcessImage(net.io.sizes)
            before = None  # a new image holds no symbol's value
        if net is not self.net:  # a download: which values another program left here
            old = self.net.name if self.net is not None else net.name
            kept = memory.initialized(self.image, net.io, before, old == net.name)
            self.kept_across = memory.Kept(old, kept) if kept else None
        if clear:
            memory.unretained(self.image, net.io)
        if engine is not None and engine.net is net and engine is not self.engine:
            engine.state = state  # tables built off the scan; only the state is new
            engine.invalidate()
        else:
            engine = Engine(net, state)
        self.net, self.engine = net, engine
        self.stopped_at_ns = None
        self.locations = {s.name: (s.address.attr, s.address.index)
                          for s in net.io.symbols.values()}
        self.typed = {s.name: s.type for s in net.io.symbols.values() if s.type not in _PLAIN}
        by_location: dict[tuple[str, int], list[str]] = {}
        for name, loc in self.locations.items():
            by_location.setdefault(loc, []).append(name)
        self.by_location = {k: tuple(v) for k, v in by_location.items()}
        self.events = event_conditions.EventMemory()
        self.forces.rebind(net.io.symbols)  # forces on symbols the program lacks are dropped
        self.debug.rebind(net)  # so are breakpoints on what it lacks (with a note)

    # -- forcing (docs/design.md section 10) -----------------------------------------------------

    def _force(self, cmd: ProgramCommand) -> str:
        """FORCE/UNFORCE: the state stays. Forced outputs act only while RUNNING (stopped,
        killed or faulted outputs stay safe whatever is forced); forced inputs always."""
        try:
            if cmd.command is Command.UNFORCE:
                released = self.forces.release(cmd.symbol)
                for entry, shadow in released:
                    self._unshadow(entry, shadow)
                if self.engine is not None:
                    self.engine.refresh_outputs()  # place-driven outputs: the marking's again
                names = ", ".join(e.symbol for e, _ in released)
                return f"unforce: released {names or 'nothing (no symbol was forced)'}"
            if self.net is None:
                raise ForceRefused(f"no program is loaded (state {self.state.name}; force is "
                                   f"accepted in {accepting(Command.FORCE)})")
            if cmd.symbol is None:
                raise ForceRefused("force needs a symbol")
            entry = self.forces.force(self.net.io.symbols, cmd.symbol, cmd.value, self.image)
        except ForceRefused as exc:
            raise CommandRejected(self.state, cmd.command, f"{cmd.command.value} refused: "
                                  f"{exc}") from None
        shown = shown_rounded(entry.type.value if entry.type else None, entry.value,
                              entry.scaling)  # at its scale's resolution (core/present.py)
        return f"force: {entry.symbol} = {shown} (state {self.state.name})"

    def _unshadow(self, entry: Force, shadow: int | None) -> None:
        """A released output gets the program's value back (image while RUNNING, the outputs
        held at a stop otherwise)."""
        if shadow is None:
            return
        held = self.held or self.debug.held  # stopped, or paused with safe outputs out
        if self.state is PlcState.RUNNING and held is None:
            arr = getattr(self.image, entry.area)
            arr[entry.index] = bool(shadow) if entry.area.endswith("x") else shadow
        elif held is not None:
            held.put(entry.area, entry.index, shadow)

    def unpause(self, now_ns: int | None, steps: int = 0) -> None:
        """The net runs again after a pause: `steps` scans (0: until a breakpoint hits), or
        it stops, is killed or faults. Its timers skip the time spent paused (docs/debug.md)."""
        shift, held = self.debug.leave(now_ns, steps)
        self._shift_timers(shift)
        if held is not None:
            held.restore(self.image)  # the `safe` policy put the program's outputs aside

    def _thaw(self, now_ns: int) -> None:
        """Timers were frozen at stop: shift them by the time spent stopped."""
        if self.engine is None or self.stopped_at_ns is None:
            return
        self._shift_timers(now_ns - self.stopped_at_ns)
        self.stopped_at_ns = None

    def _shift_timers(self, shift: int) -> None:
        if self.engine is None or not shift:
            return
        st = self.engine.state
        st.enabled_since = {t: since + shift for t, since in st.enabled_since.items()}
        st.busy = {t: Busy(b.end_ns + shift, b.produce) for t, b in st.busy.items()}
        self.engine.invalidate()

    # -- start-up: waiting for the first input image (docs/faults.md, start-up) ---------------

    def awaited(self, answering: Mapping[str, bool]) -> tuple[str, ...]:
        """The devices whose first input image the program still waits for: drivers its io
        image declares that the runtime has not opened as declared, and observed devices that
        never answered and whose fault policy has not decided yet (a FAULT verdict faults)."""
        ready, opened = self._io_ready, self.open_devices
        if ready and ready[0] is self.net and ready[1] is opened and ready[2] is answering:
            return ()  # the steady scan: a device that answered once has delivered
        waiting = awaited_devices(self.net.io.drivers if self.net else None, opened,
                                  answering, self.devices.watches)
        self._io_ready = None if waiting else (self.net, opened, answering)
        return waiting

    def wait_for_io(self, now_ns: int) -> None:
        """RUNNING without every device's first input image: no round, timers frozen, safe
        outputs; the program's outputs are kept for when the wait ends."""
        if self.io_wait is None:
            self.io_wait = IoWait(now_ns, HeldOutputs.of(self.image))
        self.drive_safe()

    def end_io_wait(self, now_ns: int | None) -> None:
        """Every device delivered, or a command or fault: timers continue with the time they
        had left, the program's outputs come back (without `now_ns` nothing is kept)."""
        if self.io_wait is None:
            return
        wait, self.io_wait = self.io_wait, None
        if now_ns is not None:
            self._shift_timers(now_ns - wait.since_ns)
            wait.outputs.restore(self.image)

    def _online_change(self, cmd: ProgramCommand, carry_plan: CarryPlan) -> str:
        """A download while RUNNING of the same program, accepted by core/verdict.py
        (docs/programs.md, online change; core/online.py)."""
        assert self.net is not None and self.engine is not None and cmd.net is not None
        net = cmd.net
        carried = online.carry(carry_plan, self.engine.state)
        if isinstance(carried, str):
            raise CommandRejected(self.state, Command.DOWNLOAD, carried)
        self._load(net, carried, cmd.engine)
        fresh = len(carry_plan.fresh)
        return (f"online change to {net.name} ({net.program_hash[:12]})"
                + (f", {fresh} new place(s) with their declared tokens" if fresh else ""))

    def _replace(self, cmd: ProgramCommand) -> str:
        """Another program while RUNNING, accepted by core/verdict.py. On other devices it is
        the seed paper's reconfiguration (the machine changed too); on the same devices the
        tokens of the running program stand for real parts, so it needed `replace`."""
        assert self.net is not None and cmd.net is not None
        old, net = self.net, cmd.net
        same_devices = tuple(old.io.drivers.values()) == tuple(net.io.drivers.values())
        self._load(net, NetState.initial(net), cmd.engine)
        self.drive_safe()  # outputs the new program does not drive must not stay on
        self.first_round = True
        why = "replacement" if same_devices else "replacement with new devices (reconfiguration)"
        return (f"online {why}: {old.name} -> {net.name} ({net.program_hash[:12]}), "
                "initial marking" + (self.kept_across.note() if self.kept_across else ""))

    def fault(self, code: FaultCode, now_ns: int | None = None, reason: str = "") -> None:
        """Watchdog, device, program or limit fault: FAULTED, outputs safe (the caller or the
        next scan writes them).

        With `now_ns`, timers freeze and the outputs are kept as at a stop, so that recover()
        can continue where the program was; without it nothing is kept for later."""
        if self.state is PlcState.RUNNING:
            self.end_io_wait(now_ns)
            self.unpause(now_ns)
            self.stopped_at_ns = now_ns
            self.held = None if now_ns is None else HeldOutputs.of(self.image)
        if self.state in (PlcState.RUNNING, PlcState.STOPPED):
            self.state = PlcState.FAULTED
            self.fault_code, self.fault_reason = FaultCode(code), reason or code.name.lower()
            self.drive_safe()

    def recover(self, now_ns: int) -> bool:
        """Device auto-recovery: FAULTED by a device while RUNNING -> RUNNING as a resume
        would (marking kept, timers shifted by the time faulted, outputs as they were).
        Not a lifecycle command: the table has no way out of FAULTED but reset/download."""
        if (self.state is not PlcState.FAULTED or self.fault_code != FAULT_DEVICE
                or self.held is None):
            return False
        self._thaw(now_ns)
        self.held.restore(self.image)
        self.held = None
        self.state, self.fault_code, self.fault_reason = PlcState.RUNNING, FAULT_NONE, ""
        self.first_round = True
        self.events.rearm()
        return True

    # -- image ------------------------------------------------------------------------------

    def apply_hmi(self, writes: Iterable[HmiWrite]) -> None:
        """All at the scan boundary, in one go: a %MD's two registers written by one request
        are never seen half by the program (docs/modbus.md)."""
        for write in writes:
            if write.address.area is not Area.INPUT:  # inputs belong to the drivers
                self.image.write_registers(write.address, write.values)

    def drive_safe(self) -> None:
        drive_safe(self.image, self.net.io.symbols.values() if self.net else ())
