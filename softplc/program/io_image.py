"""Load an `io_images/*.yaml` symbols file into an IoImage, collecting every problem.

Owns: the symbols file format (image sizes, drivers with their fault policy, symbols, event
conditions); the values a symbol declares (scale, safe, init) are program/symvalues.py's.
Does not know: programs, drivers' internals.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import MappingProxyType
from typing import Any

from softplc.core.datatypes import INFO, NATURAL, TYPE_NAMES, fits, types_for
from softplc.core.image import (
    Address,
    AddressError,
    ImageSizes,
    ProcessImage,
    Width,
    parse_address,
)
from softplc.core.problems import Problem, ProgramError
from softplc.core.symbols import (
    DIRECTION_OF_AREA,
    Direction,
    DriverSpec,
    EventKind,
    EventSpec,
    FaultPolicy,
    IoImage,
    OnFailure,
    Retain,
    Symbol,
    SymType,
)
from softplc.program import symvalues
from softplc.program.suggest import did_you_mean, did_you_mean_key
from softplc.program.yamlload import YMap, line_of, load_yaml, trap_hint

DRIVER_KINDS = ("sim", "modbus", "modbus_rtu", "opcua")
POLICY_KEYS = ("on_failure", "hold_scans", "auto_recover", "startup_s")  # any kind of driver
SYMBOL_KEYS = {"address", "type", "dir", "safe", "driver", "channel", "description", "hmi_writable",
               "retain", "scale", "init", "finite"}


class _Reader:
    def __init__(self, filename: str) -> None:
        self.file = filename
        self.problems: list[Problem] = []

    def problem(self, line: int, path: str, message: str) -> None:
        self.problems.append(Problem(self.file, line, path, message))

    def section(self, data: YMap, key: str) -> YMap:
        value = data.get(key, YMap())
        if not isinstance(value, dict):
            self.problem(line_of(data, key), key, "expected a mapping of name: {...}")
            return YMap()
        return value  # type: ignore[return-value]

    def sizes(self, data: YMap) -> ImageSizes:
        spec = data.get("image") or {}
        try:
            return ImageSizes(bits=int(spec.get("bits", 800)), words=int(spec.get("words", 1024)),
                              dwords=int(spec.get("dwords", -1)),
                              lwords=int(spec.get("lwords", -1)))
        except (TypeError, ValueError, AttributeError) as exc:
            self.problem(line_of(data, "image"), "image", f"bad image sizes: {exc}")
            return ImageSizes()

    def drivers(self, data: YMap) -> dict[str, DriverSpec]:
        out: dict[str, DriverSpec] = {}
        section = self.section(data, "drivers")
        for name, spec in section.items():
            line, path = line_of(section, name), f"drivers.{name}"
            if not isinstance(spec, dict) or spec.get("kind") not in DRIVER_KINDS:
                kind = spec.get("kind") if isinstance(spec, dict) else None
                hint = did_you_mean(kind, DRIVER_KINDS) if isinstance(kind, str) else ""
                self.problem(line, path,
                             f"expected {{kind: {' | '.join(DRIVER_KINDS)}, ...}}{hint}")
                continue
            params = {k: v for k, v in spec.items() if k != "kind" and k not in POLICY_KEYS}
            policy = self.policy(spec, path)
            out[str(name)] = DriverSpec(str(name), str(spec["kind"]), MappingProxyType(params),
                                        line, policy)
        return out

    def policy(self, spec: dict[Any, Any], path: str) -> FaultPolicy:
        """The device fault policy keys of one driver; defaults for any that is bad."""
        default = FaultPolicy()
        on_failure = self._on_failure(spec, path)
        hold_scans = spec.get("hold_scans", 0)
        if "hold_scans" in spec and (not _is_int(hold_scans) or hold_scans < 1):
            self.problem(line_of(spec, "hold_scans"), f"{path}.hold_scans",
                         f"hold_scans must be an integer >= 1, got {hold_scans!r}")
            hold_scans = 0
        elif on_failure is OnFailure.HOLD and "hold_scans" not in spec:
            self.problem(line_of(spec, "on_failure"), f"{path}.on_failure",
                         "on_failure: hold needs hold_scans: N (scans to hold the last inputs)")
        elif on_failure is OnFailure.FAULT and "hold_scans" in spec:
            self.problem(line_of(spec, "hold_scans"), f"{path}.hold_scans",
                         "hold_scans needs on_failure: hold (fault faults at once)")
            hold_scans = 0
        auto = spec.get("auto_recover", default.auto_recover)
        if not isinstance(auto, bool):
            self.problem(line_of(spec, "auto_recover"), f"{path}.auto_recover",
                         f"auto_recover must be true or false{trap_hint(auto)}")
            auto = default.auto_recover
        startup = spec.get("startup_s", default.startup_s)
        if isinstance(startup, bool) or not isinstance(startup, int | float) or startup < 0:
            self.problem(line_of(spec, "startup_s"), f"{path}.startup_s",
                         f"startup_s must be a number of seconds >= 0, got {startup!r}")
            startup = default.startup_s
        return FaultPolicy(on_failure, int(hold_scans), auto, float(startup))

    def _on_failure(self, spec: dict[Any, Any], path: str) -> OnFailure:
        value = spec.get("on_failure", OnFailure.FAULT.value)
        try:
            return OnFailure(value)
        except ValueError:
            choices = " or ".join(f.value for f in OnFailure)
            self.problem(line_of(spec, "on_failure"), f"{path}.on_failure",
                         f"on_failure {value!r}: expected {choices}")
            return OnFailure.FAULT

    def symbol(self, name: str, spec: Any, line: int, drivers: dict[str, DriverSpec],
               image: ProcessImage) -> Symbol | None:
        path = f"symbols.{name}"
        if not isinstance(spec, dict) or "address" not in spec:
            self.problem(line, path, "expected {address: '%IX0.0', type: bool, ...}")
            return None
        for key in sorted(set(spec) - SYMBOL_KEYS, key=str):
            self.problem(line_of(spec, key), f"{path}.{key}",
                         f"unknown key {key!r}{did_you_mean_key(key, SYMBOL_KEYS)}; "
                         f"expected one of {', '.join(sorted(SYMBOL_KEYS))}")
        try:
            address = parse_address(str(spec["address"]))
            image.check(address)
        except AddressError as exc:
            self.problem(line_of(spec, "address"), f"{path}.address", str(exc))
            return None
        sym_type = self._type(spec, path, address)
        direction = DIRECTION_OF_AREA[address.area]
        if "dir" in spec and spec["dir"] != direction.value:
            self.problem(line_of(spec, "dir"), f"{path}.dir",
                         f"dir {spec['dir']!r} contradicts address {address} ({direction.value})")
        driver = spec.get("driver")
        if "driver" not in spec and direction is not Direction.MEMORY and len(drivers) == 1:
            driver = next(iter(drivers))  # one driver: it serves every I/O symbol by default
        if driver == "none":
            driver = None  # kept in the image only (e.g. a value shown to HMIs)
        if driver is not None and driver not in drivers:
            self.problem(line_of(spec, "driver"), f"{path}.driver",
                         f"unknown driver {driver!r}{did_you_mean(driver, [*drivers, 'none'])}")
        scaling = symvalues.scale(spec, path, sym_type, self.problem)
        safe = symvalues.safe(spec, path, sym_type, scaling, self.problem)
        init = symvalues.init(spec, name, path, sym_type, direction, scaling, self.problem)
        return Symbol(name, address, sym_type, direction, safe, str(spec.get("description", "")),
                      driver, str(spec.get("channel", name)),
                      spec.get("hmi_writable", True) is True, line,
                      self._retain(spec, path, direction), scaling, init,
                      symvalues.finite(spec, path, sym_type, self.problem))

    def _retain(self, spec: dict[Any, Any], path: str, direction: Direction) -> Retain:
        """Memory only: inputs are read anew every scan, outputs are the program's."""
        value = spec.get("retain", Retain.RETAIN.value)
        words = ", ".join(r.value for r in Retain)
        if direction is not Direction.MEMORY and value != Retain.RETAIN.value:
            self.problem(line_of(spec, "retain"), f"{path}.retain",
                         f"retain applies to memory symbols (%M) only, not {direction.value}")
        elif isinstance(value, str) and value in words.split(", "):
            return Retain(value)
        else:
            self.problem(line_of(spec, "retain"), f"{path}.retain",
                         f"retain {value!r}: expected one of {words}")
        return Retain.RETAIN

    def _type(self, spec: dict[Any, Any], path: str, address: Address) -> SymType:
        natural = NATURAL[address.width.value]
        declared = spec.get("type", natural.value)
        if declared not in TYPE_NAMES:
            self.problem(line_of(spec, "type"), f"{path}.type",
                         f"unknown type {declared!r}; expected one of {', '.join(TYPE_NAMES)}"
                         f"{did_you_mean(str(declared), TYPE_NAMES)}")
            return natural
        sym_type = SymType(declared)
        if not fits(sym_type, address.width.value):
            self.problem(line_of(spec, "type"), f"{path}.type",
                         f"type {declared} does not fit address {address} (a "
                         f"{_WIDTH_WORDS[address.width]} address holds "
                         f"{' or '.join(types_for(address.width.value))}; "
                         f"{symvalues.article(declared)} needs "
                         f"{_address_for(sym_type, address)})")
            return natural
        return sym_type

    def events(self, data: YMap, symbols: dict[str, Symbol]) -> dict[str, EventSpec]:
        out: dict[str, EventSpec] = {}
        section = self.section(data, "events")
        for name, spec in section.items():
            line, path = line_of(section, name), f"events.{name}"
            kinds = [k for k in EventKind if isinstance(spec, dict) and k.value in spec]
            if len(kinds) != 1:
                self.problem(line, path,
                             "expected exactly one of rising, falling, change, above, below")
                continue
            kind = kinds[0]
            target = spec[kind.value]
            sym = symbols.get(str(target))
            if sym is None:
                self.problem(line, path,
                             f"unknown symbol {target!r}{did_you_mean(target, symbols)}")
                continue
            if kind in (EventKind.RISING, EventKind.FALLING) and sym.type is not SymType.BOOL:
                self.problem(line, path, f"{kind.value} needs a bool symbol; {sym.name} is a word")
                continue
            if kind in (EventKind.ABOVE, EventKind.BELOW) and sym.type is SymType.BOOL:
                self.problem(line, path, f"{kind.value} needs a numeric symbol; {sym.name} is a "
                                         "bool")
                continue
            threshold, hysteresis = spec.get("threshold", 0), spec.get("hysteresis", 0)
            numbers = int | float if INFO[sym.type].is_float or sym.scaling else int
            if not all(isinstance(v, numbers) and not isinstance(v, bool)
                       and math.isfinite(v) for v in (threshold, hysteresis)):
                self.problem(line, path, "threshold and hysteresis must be "
                             + ("numbers" if numbers is not int else "integers (the symbol is "
                                f"a {sym.type.value}; fractions need a real or lreal)"))
                continue
            out[str(name)] = EventSpec(str(name), kind, sym.name, threshold, hysteresis, line)
        return out


_WIDTH_WORDS = {Width.BIT: "bit", Width.WORD: "16-bit word", Width.DWORD: "32-bit double word",
                Width.LWORD: "64-bit long word"}


def _address_for(sym_type: SymType, address: Address) -> str:
    letter = INFO[sym_type].width
    example = f"%{address.area.value}{letter}{0 if letter != 'X' else '0.0'}"
    return f"a %{address.area.value}{letter} address, e.g. {example}"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def parse_io_image(text: str, filename: str) -> IoImage:
    data, problems = load_yaml(text, filename)
    reader = _Reader(filename)
    reader.problems.extend(problems)
    if not isinstance(data, dict):
        if data is not None or not problems:
            reader.problem(1, "", "expected a mapping with symbols: (and drivers:, events:)")
        raise ProgramError(reader.problems)
    sizes = reader.sizes(data)  # type: ignore[arg-type]
    image = ProcessImage(sizes)
    drivers = reader.drivers(data)  # type: ignore[arg-type]
    symbols: dict[str, Symbol] = {}
    taken: dict[object, str] = {}
    section = reader.section(data, "symbols")  # type: ignore[arg-type]
    for name, spec in section.items():
        sym = reader.symbol(str(name), spec, line_of(section, name), drivers, image)
        if sym is None:
            continue
        if sym.address in taken:
            reader.problem(sym.line, f"symbols.{name}",
                           f"address {sym.address} is already used by {taken[sym.address]}")
        taken[sym.address] = sym.name
        symbols[sym.name] = sym
    events = reader.events(data, symbols)  # type: ignore[arg-type]
    for name in events:
        if name in symbols:
            reader.problem(events[name].line, f"events.{name}",
                           "an event cannot share a symbol's name")
    if reader.problems:
        raise ProgramError(sorted(reader.problems))
    return IoImage(filename, sizes, MappingProxyType(symbols), MappingProxyType(drivers),
                   MappingProxyType(events))


def hashed_text(io: IoImage) -> str:
    """The symbol table as the program hash covers it (program/compiler.py): what changes the
    PLC's behaviour, at its doors too. `init:`, `modbus: eng`, `hmi_writable: false` and
    `finite: false` only where declared, so the hashes of io images without them (and the
    golden traces that record them) stay as they were; `retain:`, descriptions and units not
    at all (texts and keeping: a change of them alone keeps a warm start). The doors keep
    what they built from the status board by this hash (the Modbus write predicate, the OPC
    UA address space, the Sparkplug door): left out of it, a download that only locked a
    symbol (`hmi_writable: false`) left Modbus writing it while HTTP refused
    (tests/security/test_lock_by_download.py)."""
    return repr(sorted((s.name, str(s.address), s.type.value, s.safe)
                       + ((s.scaling.raw, s.scaling.eng, s.scaling.clamp) if s.scaling else ())
                       + (("init", s.init_raw) if s.init_raw is not None else ())
                       + (("modbus", "eng") if s.scaling and s.scaling.modbus != "raw" else ())
                       + (("hmi_writable", False) if not s.hmi_writable else ())
                       + (("finite", False) if not s.finite else ())
                       for s in io.symbols.values()))


def load_io_image(path: str | Path) -> IoImage:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProgramError(
            [Problem(str(path), 0, "", f"cannot read symbols file: {exc.strerror}")]) from None
    return parse_io_image(text, str(path))
