"""The PLC: one scan as a function of (state, input image, now_ns, commands).

Owns: the order of a scan (docs/design.md section 1): apply commands and HMI writes at the scan
boundary; latch inputs; evaluate event conditions; one firing round when RUNNING; write the
output image (safe values unless RUNNING). Program handling per the lifecycle table, online
change with the marking carried over by place name, frozen timers while stopped.
Does not know: clocks, processes, sockets, YAML (programs arrive compiled).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from softplc.core import events as event_conditions
from softplc.core import online
from softplc.core.expr import Value
from softplc.core.faults import DeviceMonitor, Verdict
from softplc.core.firing import Engine
from softplc.core.forcing import Force, ForceRefused, Forces
from softplc.core.image import AREAS, Area, ProcessImage
from softplc.core.lifecycle import Command, CommandRejected, PlcState, accepting, next_state
from softplc.core.net import Busy, CompiledNet, NetState
from softplc.core.online import CarryPlan
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.snapshot import CommandReply, HmiWrite
from softplc.core.symbols import Direction, FaultPolicy

# Kept for readers of older code and tests: the codes are FaultCode's.
FAULT_NONE, FAULT_WATCHDOG, FAULT_DEVICE = FaultCode.NONE, FaultCode.WATCHDOG, FaultCode.DEVICE


@dataclass(frozen=True, slots=True)
class ProgramCommand:
    """A command as the scan sees it: a download carries an already compiled net."""

    command: Command
    net: CompiledNet | None = None
    online: bool = False
    id: int = 0
    symbol: str | None = None  # FORCE/UNFORCE: the symbol (UNFORCE None: release all)
    value: int = 0  # FORCE: the forced value
    replace: bool = False  # a download of another program while RUNNING: replace it
    # Built off the scan for `net` (runtime/loop.py): the engine's tables and the carry plan
    # against the running net, so that the swap costs a few array operations.
    engine: Engine | None = None
    plan: CarryPlan | None = None


@dataclass(frozen=True, slots=True)
class Observed:
    """What the runtime measured for this scan, for the PLC to judge (the scan decides, so a
    trace holding these replays every fault): each device's answer (name -> answering) and
    why the silent ones are silent; a watchdog overrun of the previous scan or a stall of the
    cycle, as the reason text ("" when none)."""

    answering: Mapping[str, bool] = field(default_factory=dict)
    why: Mapping[str, str] = field(default_factory=dict)
    overrun: str = ""
    stall: str = ""


NOTHING_OBSERVED = Observed()


@dataclass(frozen=True, slots=True)
class ScanResult:
    outputs: ProcessImage  # the PLC's image after the scan (outputs and memory committed)
    events: tuple[str, ...]  # event conditions that occurred and events the program emitted
    fired: tuple[str, ...]
    completed: tuple[str, ...]
    marking_changes: dict[str, int]
    replies: tuple[CommandReply, ...]
    outputs_changed: bool = True  # False: the output image equals the previous scan's


class _Context:
    """EvalContext over the scan's image: current values, previous values, events."""

    __slots__ = ("events", "image", "locations", "prev")

    def __init__(self, image: ProcessImage, prev: ProcessImage,
                 locations: dict[str, tuple[str, int]], events: frozenset[str]) -> None:
        self.image, self.prev, self.locations, self.events = image, prev, locations, events

    def symbol(self, name: str) -> int:
        area, index = self.locations[name]
        return int(getattr(self.image, area)[index])

    def previous(self, name: str) -> int:
        area, index = self.locations[name]
        return int(getattr(self.prev, area)[index])

    def event(self, name: str) -> bool:
        return name in self.events

    def token(self, var: str) -> dict[str, Value]:
        raise KeyError(var)


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
    held: tuple[np.ndarray, np.ndarray] | None = None  # outputs at stop, restored on resume
    written_last: set[str] = field(default_factory=set)
    scan_count: int = 0
    fault_code: FaultCode = FaultCode.NONE
    fault_reason: str = ""  # what faulted the PLC, for people (status, events)
    stopped_at_ns: int | None = None
    locations: dict[str, tuple[str, int]] = field(default_factory=dict)
    by_location: dict[tuple[str, int], tuple[str, ...]] = field(default_factory=dict)
    devices: DeviceMonitor = field(default_factory=DeviceMonitor)
    _policies_of: CompiledNet | None = None
    _policies: Mapping[str, FaultPolicy] = field(default_factory=dict)
    forces: Forces = field(default_factory=Forces)  # docs/design.md section 10
    # The device answers judged last with every device OK (scan.judge's steady scan), if so.
    steady_answers: Mapping[str, bool] | None = None
    context: _Context | None = None  # the guards' view of the image, kept between scans

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

    # -- program handling -------------------------------------------------------------------

    def apply(self, cmd: ProgramCommand, now_ns: int) -> str:
        """Apply one command. Raises CommandRejected and changes nothing when refused."""
        if cmd.command is Command.FORCE or cmd.command is Command.UNFORCE:
            return self._force(cmd)
        target = next_state(self.state, cmd.command)
        if cmd.command is Command.DOWNLOAD:
            if cmd.net is None:
                raise CommandRejected(self.state, cmd.command, "download without a program")
            if self.state is PlcState.RUNNING:
                return self._online_change(cmd)
            self._load(cmd.net, NetState.initial(cmd.net), cmd.engine)
        elif cmd.command is Command.START or cmd.command is Command.RESET:
            assert self.net is not None
            self._load(self.net, NetState.initial(self.net))
            self.forces.release(None)  # a cold start drops every force (docs/design.md section 10)
        elif cmd.command is Command.RESUME:
            self._thaw(now_ns)
        if target is not PlcState.RUNNING and self.state is PlcState.RUNNING:
            self.stopped_at_ns = now_ns
            self.held = (self.image.qx.copy(), self.image.qw.copy())
        if cmd.command is Command.RESUME and self.held is not None:
            np.copyto(self.image.qx, self.held[0])
            np.copyto(self.image.qw, self.held[1])
        if cmd.command is not Command.STOP:
            self.held = None
        self.state = target
        if target is not PlcState.FAULTED:
            self.fault_code, self.fault_reason = FAULT_NONE, ""
        return f"{cmd.command.value}: now {target.name}"

    def _load(self, net: CompiledNet, state: NetState, engine: Engine | None = None) -> None:
        if net.io.sizes != self.image.sizes:
            self.image, self.prev = ProcessImage(net.io.sizes), ProcessImage(net.io.sizes)
        if engine is not None and engine.net is net and engine is not self.engine:
            engine.state = state  # tables built off the scan; only the state is new
            engine.invalidate()
        else:
            engine = Engine(net, state)
        self.net, self.engine = net, engine
        self.stopped_at_ns = None
        self.locations = {s.name: (s.address.attr, s.address.index)
                          for s in net.io.symbols.values()}
        by_location: dict[tuple[str, int], list[str]] = {}
        for name, loc in self.locations.items():
            by_location.setdefault(loc, []).append(name)
        self.by_location = {k: tuple(v) for k, v in by_location.items()}
        self.events = event_conditions.EventMemory()
        self.forces.rebind(net.io.symbols)  # forces on symbols the program lacks are dropped

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
        return f"force: {entry.symbol} = {entry.value} (state {self.state.name})"

    def _unshadow(self, entry: Force, shadow: int | None) -> None:
        """A released output gets the program's value back (image while RUNNING, the outputs
        held at a stop otherwise)."""
        if shadow is None:
            return
        value = bool(shadow) if entry.area.endswith("x") else shadow
        if self.state is PlcState.RUNNING:
            getattr(self.image, entry.area)[entry.index] = value
        elif self.held is not None and entry.area in ("qx", "qw"):
            self.held[0 if entry.area == "qx" else 1][entry.index] = value

    def _thaw(self, now_ns: int) -> None:
        """Timers were frozen at stop: shift them by the time spent stopped."""
        if self.engine is None or self.stopped_at_ns is None:
            return
        shift = now_ns - self.stopped_at_ns
        st = self.engine.state
        st.enabled_since = {t: since + shift for t, since in st.enabled_since.items()}
        st.busy = {t: Busy(b.end_ns + shift, b.produce) for t, b in st.busy.items()}
        self.engine.invalidate()
        self.stopped_at_ns = None

    def _online_change(self, cmd: ProgramCommand) -> str:
        """A download while RUNNING (docs/programs.md, online change; core/online.py)."""
        assert self.net is not None and self.engine is not None and cmd.net is not None
        net, old = cmd.net, self.net
        if not cmd.online:
            raise CommandRejected(self.state, Command.DOWNLOAD,
                                  "download while RUNNING needs online change (--online), "
                                  "or stop the program first (a plain download is accepted in "
                                  f"{accepting(Command.DOWNLOAD).replace(', RUNNING', '')})")
        if net.name != old.name:
            return self._replace(cmd)
        carry_plan = cmd.plan if cmd.plan is not None and cmd.plan.old is old \
            and cmd.plan.new is net else online.plan(old, net)
        carried = online.carry(carry_plan, self.engine.state)
        if isinstance(carried, str):
            raise CommandRejected(self.state, Command.DOWNLOAD, carried)
        self._load(net, carried, cmd.engine)
        fresh = len(carry_plan.fresh)
        return (f"online change to {net.name} ({net.program_hash[:12]})"
                + (f", {fresh} new place(s) with their declared tokens" if fresh else ""))

    def _replace(self, cmd: ProgramCommand) -> str:
        """Another program while RUNNING. On other devices it is the seed paper's
        reconfiguration (the machine changed too) and goes ahead; on the same devices the
        tokens of the running program stand for real parts, so it needs `replace`."""
        assert self.net is not None and cmd.net is not None
        old, net = self.net, cmd.net
        same_devices = tuple(old.io.drivers.values()) == tuple(net.io.drivers.values())
        if same_devices and not cmd.replace:
            marked = int(np.count_nonzero(self.engine.state.marking)) if self.engine else 0
            raise CommandRejected(self.state, Command.DOWNLOAD, (
                f"online change refused: {net.name} is another program than the running "
                f"{old.name} on the same devices; it would start from its initial marking and "
                f"drop the tokens of {marked} marked place(s). Replace it explicitly "
                "(--replace), or stop first"))
        self._load(net, NetState.initial(net), cmd.engine)
        self.drive_safe()  # outputs the new program does not drive must not stay on
        why = "replacement" if same_devices else "replacement with new devices (reconfiguration)"
        return (f"online {why}: {old.name} -> {net.name} ({net.program_hash[:12]}), "
                "initial marking")

    def fault(self, code: FaultCode, now_ns: int | None = None, reason: str = "") -> None:
        """Watchdog, device, program or limit fault: FAULTED, outputs safe (the caller or the
        next scan writes them).

        With `now_ns`, timers freeze and the outputs are kept as at a stop, so that recover()
        can continue where the program was; without it nothing is kept for later."""
        if self.state is PlcState.RUNNING:
            self.stopped_at_ns = now_ns
            self.held = None if now_ns is None else (self.image.qx.copy(), self.image.qw.copy())
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
        np.copyto(self.image.qx, self.held[0])
        np.copyto(self.image.qw, self.held[1])
        self.held = None
        self.state, self.fault_code, self.fault_reason = PlcState.RUNNING, FAULT_NONE, ""
        return True

    # -- image ------------------------------------------------------------------------------

    def apply_hmi(self, writes: Iterable[HmiWrite]) -> None:
        for write in writes:
            arr = self.image.area(write.address.area, write.address.width)
            if write.address.area is Area.INPUT:
                continue  # the HMI map refuses these; inputs belong to the drivers
            start = write.address.index
            values = np.asarray(write.values[: max(len(arr) - start, 0)])
            if write.address.is_bit:
                arr[start:start + len(values)] = values != 0
            else:
                arr[start:start + len(values)] = values.astype(np.int64) & 0xFFFF

    def drive_safe(self) -> None:
        self.image.qx[:] = False
        self.image.qw[:] = 0
        if self.net is None:
            return
        for sym in self.net.io.symbols.values():
            if sym.direction is Direction.OUT:
                self.image.set(sym.address, sym.safe)

    def _changed(self) -> set[str]:
        changed: set[str] = set()
        image, prev = self.image, self.prev
        if (image.buf is not None and prev.buf is not None
                and image.buf.tobytes() == prev.buf.tobytes()):
            return changed  # the common scan: one comparison of the whole image
        for area in AREAS:
            now, before = getattr(self.image, area), getattr(self.prev, area)
            if now.tobytes() == before.tobytes():
                continue
            for index in np.flatnonzero(now != before).tolist():
                changed.update(self.by_location.get((area, index), ()))
        return changed

    def _write(self, writes: Iterable[tuple[str, int]]) -> None:
        for symbol, value in writes:
            area, index = self.locations[symbol]
            arr = getattr(self.image, area)
            arr[index] = bool(value) if area.endswith("x") else (int(value) & 0xFFFF)


def scan(plc: Plc, inputs: ProcessImage, now_ns: int,
         commands: Sequence[ProgramCommand] = (), hmi: Sequence[HmiWrite] = (),
         observed: Observed = NOTHING_OBSERVED) -> ScanResult:
    """One scan. `plc` is advanced in place and must not be used by anyone else meanwhile;
    `inputs` is only read (its %I areas are latched).

    `observed` is what the runtime measured (device answers, an overrun, a stall): the scan
    judges it before the program runs, per the fault policies (docs/design.md section 8).
    Nothing raised inside a scan escapes it: PlcFault (a limit, a program error) and any
    other exception (a bug) fault the PLC with safe outputs and the reason, and the scan
    returns as a scan of a FAULTED PLC would: faults, not deaths."""
    judged = judge(plc, observed, now_ns)
    replies = _apply_commands(plc, commands, now_ns)
    killed = bool(commands) and any(c.command is Command.KILL and r.ok
                                    for c, r in zip(commands, replies, strict=True))
    try:
        result = _scan_body(plc, inputs, now_ns, commands, hmi, replies, killed)
    except PlcFault as exc:
        result = _faulted(plc, inputs, now_ns, replies, exc.code, exc.reason)
    except Exception as exc:  # a bug of softplc or of a program path we did not foresee
        reason = f"internal error in the scan: {type(exc).__name__}: {exc}"
        result = _faulted(plc, inputs, now_ns, replies, FaultCode.INTERNAL, reason)
    after = plc.devices.after_scan(plc, now_ns) if observed.answering else []
    if judged or after:
        events = (*judged, *result.events, *after)
        result = ScanResult(result.outputs, events, result.fired, result.completed,
                            result.marking_changes, result.replies, True)
    return result


def judge(plc: Plc, observed: Observed, now_ns: int) -> list[str]:
    """The runtime's measurements, judged before the scan's commands and program. The
    runtime also calls it between scans for a watchdog overrun, so safe outputs go out at
    once; the trace then carries the observation with the next scan."""
    if not observed.overrun and not observed.stall:
        if not observed.answering or _quiet(plc, observed.answering):
            return []  # the steady scan: nothing measured, or every device as it was
        return _judge_devices(plc, observed, now_ns)
    events: list[str] = []
    for code, reason in ((FaultCode.WATCHDOG, observed.overrun),
                         (FaultCode.STALL, observed.stall)):
        if reason and plc.state is PlcState.RUNNING:
            plc.fault(code, None, reason)
            events.append(f"plc_fault:{code.name.lower()}")
    if observed.answering:
        events += _judge_devices(plc, observed, now_ns)
    return events


def _judge_devices(plc: Plc, observed: Observed, now_ns: int) -> list[str]:
    devices = plc.devices
    events = devices.before_scan(plc, observed.answering, plc.policies(),
                                 lambda name: observed.why.get(name, "not answering"), now_ns)
    # The same answers again next scan change nothing (DeviceMonitor.before_scan would only
    # look at every device to find it answering), as long as every watch stays OK.
    steady = (not events and all(observed.answering.values())
              and len(devices.watches) == len(observed.answering)
              and all(w.verdict is Verdict.OK for w in devices.watches.values()))
    plc.steady_answers = observed.answering if steady else None
    return events


def _quiet(plc: Plc, answering: Mapping[str, bool]) -> bool:
    """`answering` is the mapping last judged steady, and the device monitor has nothing to
    do: no failed device, no device fault to recover from, no culprits to clear."""
    devices = plc.devices
    return (answering is plc.steady_answers and not devices.failed and not devices.culprits
            and len(devices.watches) == len(answering)
            and (plc.state is not PlcState.FAULTED or plc.fault_code != FAULT_DEVICE))


def _apply_commands(plc: Plc, commands: Sequence[ProgramCommand],
                    now_ns: int) -> list[CommandReply]:
    replies = []
    for cmd in commands:
        try:
            message = plc.apply(cmd, now_ns)
            replies.append(CommandReply(cmd.id, True, message, plc.state))
        except CommandRejected as exc:
            replies.append(CommandReply(cmd.id, False, exc.reason, plc.state))
        except Exception as exc:  # a swap that failed half-way: the PLC must not go on with it
            reason = f"{cmd.command.value} failed: {type(exc).__name__}: {exc}"
            plc.fault(FaultCode.INTERNAL, None, reason)
            replies.append(CommandReply(cmd.id, False, reason, plc.state))
    return replies


def _faulted(plc: Plc, inputs: ProcessImage, now_ns: int, replies: list[CommandReply],
             code: FaultCode, reason: str) -> ScanResult:
    """The end of a scan whose execution raised: FAULTED (from any state that runs a program),
    outputs safe, inputs latched, the scan counted."""
    if plc.state is PlcState.RUNNING or plc.state is PlcState.STOPPED:
        plc.fault(code, now_ns if plc.state is PlcState.RUNNING else None, reason)
    plc.drive_safe()
    plc.last_events = plc.true_last = frozenset()
    np.copyto(plc.image.ix, inputs.ix)
    np.copyto(plc.image.iw, inputs.iw)
    plc.forces.apply_inputs(plc.image)  # forced inputs show in every state
    if plc.engine is not None:
        plc.engine.invalidate()  # a round that raised half-way leaves no cached enabling
    plc.image.copy_into(plc.prev)
    plc.scan_count += 1
    return ScanResult(plc.image, (f"plc_fault:{code.name.lower()}",), (), (), {},
                      tuple(replies), True)


def _scan_body(plc: Plc, inputs: ProcessImage, now_ns: int,
               commands: Sequence[ProgramCommand], hmi: Sequence[HmiWrite],
               replies: list[CommandReply], killed: bool) -> ScanResult:
    if hmi and not killed:
        plc.apply_hmi(hmi)
        if plc.engine is not None and any(w.address.area is not Area.INPUT for w in hmi):
            plc.engine.refresh_outputs()  # a program-driven output stays the program's
    plc.image.latch_inputs(inputs)
    plc.forces.apply_inputs(plc.image)  # forcing: a forced input replaces the driver's value
    occurred: tuple[str, ...] = ()
    fired: tuple[str, ...] = ()
    completed: tuple[str, ...] = ()
    changes: dict[str, int] = {}
    if plc.net is not None:
        occurred = event_conditions.evaluate(plc.net.io.events.values(), plc.net.io.symbols,
                                             plc.image, plc.events)
    if plc.state is PlcState.RUNNING and plc.engine is not None and plc.net is not None:
        # The steady scan allocates no sets: empty ones are shared (issue 15.5).
        now_events = (frozenset(occurred) | plc.last_events if occurred or plc.last_events
                      else _NO_EVENTS)
        plc.forces.unapply_outputs(plc.image)  # forcing: the program sees its own values
        ctx = plc.context
        if (ctx is None or ctx.image is not plc.image or ctx.prev is not plc.prev
                or ctx.locations is not plc.locations):
            ctx = plc.context = _Context(plc.image, plc.prev, plc.locations, now_events)
        ctx.events = now_events  # one context per image and program, not one per scan
        # Symbols the program wrote last scan count as changed too: the end-of-scan image
        # already holds them, so the image difference alone would miss them.
        changed = plc._changed()
        for more in (now_events, plc.true_last, plc.written_last):
            if more:
                changed |= more
        before = plc.engine.state.marking.copy()
        plc.engine.scan = plc.scan_count  # diagnostics name the scan
        step = plc.engine.fire_round(ctx, now_ns, changed)
        if step.writes:
            plc._write(step.writes)
            plc.written_last = {symbol for symbol, _ in step.writes}
        elif plc.written_last:
            plc.written_last = set()
        plc.forces.apply_outputs(plc.image)  # forcing: after Moore/Mealy, before the drivers
        names = plc.net.transitions
        if step.fired:
            fired = tuple(names[t].name for t in step.fired)
        if step.completed:
            completed = tuple(names[t].name for t in step.completed)
        if step.changed_places:
            after = plc.engine.state.marking
            changes = {plc.net.place_names[p]: int(after[p])
                       for p in sorted(step.changed_places) if after[p] != before[p]}
        emitted = step.emitted
        plc.last_events = frozenset(emitted) if emitted else _NO_EVENTS
        plc.true_last = now_events
        if emitted:
            occurred = occurred + emitted
    else:
        plc.last_events = plc.true_last = frozenset()
        plc.drive_safe()
    outputs_changed = bool(commands or hmi or fired or completed
                           or plc.state is not PlcState.RUNNING
                           or not _same_outputs(plc.image, plc.prev))
    plc.image.copy_into(plc.prev)
    plc.scan_count += 1
    return ScanResult(plc.image, occurred, fired, completed, changes, tuple(replies),
                      outputs_changed)


def _same_outputs(a: ProcessImage, b: ProcessImage) -> bool:
    return a.outputs_bytes() == b.outputs_bytes()  # one memcmp of the contiguous tail


_NO_EVENTS: frozenset[str] = frozenset()
