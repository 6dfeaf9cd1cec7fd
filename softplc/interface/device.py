"""The generic device interface of the seed paper (section 3.2, Fig. 2) over a local PLC.

Owns: DeviceInterface (variable handling, program handling, event management) in Python style
and, on the same object, the paper's facade (readDB ... notifyEvent with its 0/-1 codes);
open_device(); the device's write journal, event subscriptions and virtual clock.
Does not know: plant physics, Modbus, the real clock (time moves only through step/run_for).
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import SupportsIndex, TypeVar

from softplc.core.events import EventMemory, evaluate
from softplc.core.image import (
    WORD_MAX,
    Address,
    AddressError,
    Area,
    ProcessImage,
    Width,
    parse_address,
)
from softplc.core.lifecycle import Command, CommandRejected, PlcState
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.problems import ProgramError
from softplc.core.result import ScanResult
from softplc.core.snapshot import HmiWrite
from softplc.core.symbols import EventKind, EventSpec, IoImage, Symbol
from softplc.devices.driver import (
    DeviceError,
    DeviceUnavailable,
    Driver,
    Health,
    ProgramHandlingError,
    UnknownAddress,
    WrongDirection,
    WrongType,
)
from softplc.interface.facade import PaperProgramHandling
from softplc.program.compiler import Summary, compile_file, summarize
from softplc.program.io_image import load_io_image
from softplc.runtime.runner import ScanRunner, open_drivers

DEFAULT_PERIOD_NS = 10_000_000
T = TypeVar("T")


class UnknownEvent(DeviceError):
    """An event that is neither a declared event condition nor a symbol, or not subscribed."""


@dataclass(frozen=True, slots=True)
class Notification:
    """One occurrence of a subscribed event condition."""

    scan: int  # number of the scan that saw it (0 = the device's first scan)
    time_ns: int  # virtual time of that scan
    event: str  # event condition name, or symbol name for a change subscription


def open_device(io_image_path: str | Path, *, seed: int = 0) -> DeviceInterface:
    """A device for the drivers that `io_image_path` declares (sim plants seeded with `seed`)."""
    try:
        io = load_io_image(io_image_path)
    except ProgramError as exc:
        raise DeviceError(f"cannot open device {io_image_path}:\n{exc}") from exc
    try:
        drivers = open_drivers(io, seed)
    except ValueError as exc:  # e.g. an unknown plant name
        raise DeviceError(f"cannot open device {io_image_path}: {exc}") from exc
    return DeviceInterface(io, drivers)


class DeviceInterface(PaperProgramHandling):
    """One automation device: the drivers of an io image around a local PLC, in virtual time.

    Timing: `step()` runs one scan (drivers read, scan, drivers write) at `now_ns`, then
    advances `now_ns`. Reads see the image of the last scan (all zeros before the first).
    Writes are journaled like HMI writes and applied at the next scan boundary, before the
    program runs: an output that the program drives belongs to the program, which overwrites
    the write (an action when it fires; a place-attached output, in the present core, only
    when the marking of its places next changes), and while no program is RUNNING every
    output is driven to its safe value. Memory (%M) writes stick. Program commands act at
    once, between two scans, exactly as if passed to the next scan (a kill drops pending writes).

    Programs are addressed by their `program:` name or by the file given to download; None
    means the loaded program. A program must be written for the same symbols as the device.
    Errors raise DeviceError subclasses; the paper's functions return None or -1 instead and
    leave the message in `last_error`.
    """

    def __init__(self, io: IoImage, drivers: Sequence[Driver]) -> None:
        """`drivers` are open already (open_drivers opens them); close() closes them."""
        self.io = io
        self._plc = Plc.empty(ProcessImage(io.sizes))
        self._runner = ScanRunner(self._plc, drivers)
        self.now_ns = 0  # virtual time of the next scan
        self.commands: list[tuple[str, str]] = []  # (command, program) received, refused too
        self.last_error = ""
        self._journal: list[HmiWrite] = []
        self._names: frozenset[str] = frozenset()
        self._symbols: dict[str, Symbol] = dict(io.symbols)
        self._declared = tuple(io.events.values())
        self._watched = frozenset(spec.symbol for spec in self._declared)
        self._changes: dict[str, EventSpec] = {}  # symbol subscriptions, in subscription order
        self._subscribed: set[str] = set()
        self._memory = EventMemory()
        self._pending: list[Notification] = []
        self._closed = False

    # -- device -------------------------------------------------------------------------------

    @property
    def state(self) -> PlcState:
        return self._plc.state

    @property
    def drivers(self) -> tuple[Driver, ...]:
        return tuple(self._runner.drivers)

    @property
    def program(self) -> CompiledNet | None:
        return self._plc.net

    def snapshot(self) -> ProcessImage:
        """A copy of the image of the last scan."""
        return self._plc.image.copy()

    def marking(self) -> dict[str, int]:
        return self._plc.marking()

    def health(self) -> dict[str, Health]:
        return self._runner.health()

    def step(self, dt_ns: int = DEFAULT_PERIOD_NS) -> ScanResult:
        """One scan at `now_ns` with the journaled writes; then `now_ns` advances by `dt_ns`."""
        self._check_open()
        if dt_ns <= 0:
            raise ValueError(f"dt_ns must be positive, got {dt_ns}")
        writes, self._journal = tuple(self._journal), []
        result = self._runner.step(self.now_ns, hmi=writes)
        self._notice(self._plc.scan_count - 1)
        self.now_ns += dt_ns
        return result

    def run_for(self, duration_ns: int, period_ns: int = DEFAULT_PERIOD_NS) -> int:
        """`duration_ns // period_ns` scans, one every `period_ns`; returns how many ran."""
        if period_ns <= 0 or duration_ns < 0:
            raise ValueError(f"need period_ns > 0 and duration_ns >= 0, "
                             f"got {period_ns} and {duration_ns}")
        scans = duration_ns // period_ns
        for _ in range(scans):
            self.step(period_ns)
        return scans

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._runner.close()

    def __enter__(self) -> DeviceInterface:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise DeviceUnavailable(f"device {self.io.path} is closed")

    # -- variable handling --------------------------------------------------------------------

    def read(self, target: str) -> int:
        """The value of a symbol or address in the last scan's image (a bit as 0/1)."""
        return self._read(target, None)

    def read_analog(self, target: str) -> int:
        return self._read(target, Width.WORD)

    def write(self, target: str, value: int) -> None:
        """Journal a write to an output or memory location for the next scan boundary."""
        self._write(target, value, None)

    def write_analog(self, target: str, value: int) -> None:
        self._write(target, value, Width.WORD)

    def _read(self, target: str, width: Width | None) -> int:
        self._check_open()
        return self._plc.image.get(self._locate(target, width))

    def _write(self, target: str, value: object, width: Width | None) -> None:
        self._check_open()
        self._journal.append(_checked_write(self._locate(target, width), value, target))

    def _locate(self, target: str, width: Width | None = None) -> Address:
        if not isinstance(target, str):
            raise UnknownAddress(f"an address or symbol name is a string, got {target!r}")
        sym = self.io.lookup(target)
        try:
            address = sym.address if sym is not None else parse_address(target)
            self._plc.image.check(address)
        except AddressError as exc:
            raise UnknownAddress(f"{target!r} is not a symbol of {self.io.path} "
                                 f"nor an address of its image: {exc}") from None
        if width is not None and address.width is not width:
            want = "a bit" if width is Width.BIT else "a word"
            raise WrongType(f"{target!r} ({address}) is not {want}")
        return address

    # -- program handling ---------------------------------------------------------------------

    def download_program(self, file: str | Path, location: str | Path | None = None, *,
                         online: bool = False) -> Summary:
        """Compile `file` (found in the directory `location`, if given) and load it STOPPED,
        or swap it in while RUNNING when `online`. A bad program changes nothing."""
        self._check_open()
        path = Path(location) / file if location else Path(file)
        self.commands.append((Command.DOWNLOAD.value, str(path)))
        try:
            net = compile_file(path)
        except ProgramError as exc:
            raise ProgramHandlingError(f"download of {path} refused:\n{exc}") from exc
        self._check_layout(net)
        self._apply(ProgramCommand(Command.DOWNLOAD, net, online=online))
        self._names = frozenset({net.name, str(file), str(path)})
        return summarize(net)

    def _control(self, command: Command, program: str | None) -> PlcState:
        self._check_open()
        self.commands.append((command.value, program or ""))
        net = self._plc.net
        if program and net is not None and program not in self._names:
            raise ProgramHandlingError(f"{command.value} {program!r} refused: the device holds "
                                       f"program {net.name!r}")
        self._apply(ProgramCommand(command))
        return self._plc.state

    def _apply(self, command: ProgramCommand) -> None:
        try:
            self._plc.apply(command, self.now_ns)
        except CommandRejected as exc:
            raise ProgramHandlingError(_rejection(exc)) from exc
        if command.command is Command.KILL:
            self._journal.clear()

    def _check_layout(self, net: CompiledNet) -> None:
        mine, theirs = _layout(self.io), _layout(net.io)
        if mine == theirs:
            return
        differ = sorted(set(mine.items()) ^ set(theirs.items()), key=str)
        names = sorted({str(item[0]) for item in differ})
        raise ProgramHandlingError(
            f"program {net.name} is written for {net.io.path}, which does not match this "
            f"device's {self.io.path} (differs in: {', '.join(names[:8])})")

    # -- event management ---------------------------------------------------------------------

    def subscribe_event(self, name: str) -> None:
        """Subscribe to a declared event condition, or to any change of a symbol."""
        self._check_open()
        if name in self.io.events:
            self._subscribed.add(name)
        elif name in self.io.symbols:
            if name not in self._changes and name not in self._watched:
                self._forget(self.io.symbols[name])
            self._changes.setdefault(name, EventSpec(name, EventKind.CHANGE, name))
            self._subscribed.add(name)
        else:
            raise UnknownEvent(f"unknown event {name!r}: neither an event condition "
                               f"({', '.join(self.io.events) or 'none'}) nor a symbol of "
                               f"{self.io.path}")

    def _forget(self, sym: Symbol) -> None:
        """Changes count from the last scan on, not from an earlier subscription's value."""
        if self._plc.scan_count:
            self._memory.last[sym.name] = self._plc.image.get(sym.address)
        else:
            self._memory.last.pop(sym.name, None)

    def delete_event(self, name: str) -> None:
        """Stop notifying `name`; occurrences already pending stay pending."""
        self._check_open()
        if name not in self._subscribed:
            raise UnknownEvent(f"event {name!r} is not subscribed")
        self._subscribed.discard(name)
        self._changes.pop(name, None)

    def notify_event(self) -> list[Notification]:
        """The occurrences since the last call, oldest first; each is returned once."""
        pending, self._pending = self._pending, []
        return pending

    def _notice(self, scan: int) -> None:
        # Declared conditions are evaluated every scan, subscribed or not, so that their
        # edges and hysteresis do not depend on when a controller subscribes.
        specs = (*self._declared, *self._changes.values())
        for name in evaluate(specs, self._symbols, self._plc.image, self._memory):
            if name in self._subscribed:
                self._pending.append(Notification(scan, self.now_ns, name))

    # -- the paper's facade (Fig. 2): same functions, C-style return codes ---------------------

    def readDB(self, address: str) -> bool | None:
        return self._or_none(lambda: bool(self._read(address, Width.BIT)))

    def writeDB(self, address: str, value: int) -> int:
        return self._code(lambda: self._write(address, value, Width.BIT))

    def readAnalog(self, address: str) -> int | None:
        return self._or_none(lambda: self.read_analog(address))

    def writeAnalog(self, address: str, value: int) -> int:
        return self._code(lambda: self.write_analog(address, value))

    def subscribeEvent(self, event: str) -> int:
        return self._code(lambda: self.subscribe_event(event))

    def deleteEvent(self, event: str) -> int:
        return self._code(lambda: self.delete_event(event))

    def notifyEvent(self) -> list[Notification]:
        return self.notify_event()

    def _or_none(self, call: Callable[[], T]) -> T | None:
        try:
            value = call()
        except DeviceError as exc:
            self.last_error = str(exc)
            return None
        self.last_error = ""
        return value


def _checked_write(address: Address, value: object, target: str) -> HmiWrite:
    """The journal entry for a write, or the error; nothing is journaled on an error."""
    if address.area is Area.INPUT:
        raise WrongDirection(f"{target!r} ({address}) is an input: inputs belong to the drivers")
    if not isinstance(value, SupportsIndex) or (isinstance(value, bool) and not address.is_bit):
        raise WrongType(f"{target!r} ({address}) takes an integer, got {value!r}")
    number, top = operator.index(value), 1 if address.is_bit else WORD_MAX
    if not 0 <= number <= top:
        raise WrongType(f"{target!r} ({address}) takes 0..{top}, got {value!r}")
    return HmiWrite(address, (number,))


def _rejection(exc: CommandRejected) -> str:
    """A message that names the state and the command (the lifecycle's own reason may)."""
    state, command = exc.state.name, exc.command.value
    if state in exc.reason and command in exc.reason:
        return exc.reason
    return f"{command} refused in state {state}: {exc.reason}"


def _layout(io: IoImage) -> dict[str, object]:
    """What a program relies on: the image sizes and every symbol's location and kind."""
    out: dict[str, object] = {"image sizes": io.sizes}
    out.update({s.name: (s.address, s.type, s.direction) for s in io.symbols.values()})
    return out
