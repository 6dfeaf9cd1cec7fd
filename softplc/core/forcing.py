"""Forcing: the operator's override of inputs and outputs (docs/design.md section 10).

Owns: the set of forced symbols with their values, checking a force against the program's
symbol table, and the two places a force acts in a scan: `apply_inputs` right after the
input latch (a forced input replaces the driver's value) and `apply_outputs` after the firing
round's Moore/Mealy writes, before the drivers write (a forced output or memory symbol
replaces the program's value).
Does not know: where forces come from (API, CLI, page), clocks, retain files.

A forced output keeps a shadow: the value the program itself gives it. While RUNNING, each
scan puts the shadows back before the firing round (guards and set/reset actions work on the
program's own values), records the program's values after it, then writes the forced ones;
releasing a force puts its shadow back, so a released output shows what the program drives
now, not what was forced. HMI writes to a forced output or memory symbol are overridden.

Forces are keyed by symbol name and re-resolved against every newly loaded program: a force
on a symbol the new program does not declare is dropped (its address may mean something else
there).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from softplc.core.datatypes import INFO, value_of
from softplc.core.errors import SoftplcError
from softplc.core.image import ProcessImage
from softplc.core.present import Shown, shown_number
from softplc.core.scaling import Scaling
from softplc.core.symbols import Symbol, SymType


class ForceRefused(SoftplcError, ValueError):
    """A force the program cannot take: unknown symbol or a value outside its type."""


@dataclass(frozen=True, slots=True)
class Force:
    """One forced symbol: its image location and the value that replaces the real one."""

    symbol: str
    area: str  # "ix", "qw", ...: the image array
    index: int
    value: int  # raw bits, as the image holds them
    type: SymType | None = None  # the symbol's type when forced: the bits' meaning
    scaling: Scaling | None = None  # and its scaling: forces are shown in engineering units

    @property
    def is_input(self) -> bool:
        return self.area.startswith("i")


def check_value(sym: Symbol, value: int) -> int:
    """`value`, the raw bits the symbol's location will hold (bools 0/1, words 0..65535, double
    and long words 0..2^32-1 and 0..2^64-1; core/present.py turns a typed value into them),
    checked against the symbol's type: a real never forced to NaN or an infinity. Raises
    ForceRefused."""
    if sym.type is SymType.BOOL:
        if value not in (0, 1):
            raise ForceRefused(f"symbol {sym.name} is a bool: force it to 0 or 1, not {value}")
        return value
    high = (1 << INFO[sym.type].bits) - 1
    if sym.type is SymType.WORD or sym.type is SymType.UDINT:
        if not 0 <= value <= high:
            raise ForceRefused(f"symbol {sym.name} is a {sym.type.value}: force it to "
                               f"0..{high}, not {value}")
        return value
    if not 0 <= value <= high:
        raise ForceRefused(f"symbol {sym.name} is {_article(sym.type)} {sym.type.value}: a "
                           f"force carries its raw bits 0..{high}, not {value}")
    shown = value_of(sym.type, value)
    if isinstance(shown, float) and not math.isfinite(shown):
        raise ForceRefused(f"symbol {sym.name} is {_article(sym.type)} {sym.type.value}: "
                           f"force it to a finite number, not {shown}")
    return value


def _article(t: SymType) -> str:
    return "an" if t in (SymType.INT, SymType.LREAL) else "a"


class Forces:
    """The forced symbols of one PLC. Mutable (part of Plc); iteration is by symbol name so
    that the order of application, and therefore the image, is deterministic."""

    __slots__ = ("_by_name", "_inputs", "_outputs", "shadow")

    def __init__(self) -> None:
        self._by_name: dict[str, Force] = {}
        self.shadow: dict[str, int] = {}  # forced outputs/memory: the program's own value
        self._inputs: tuple[Force, ...] = ()
        self._outputs: tuple[Force, ...] = ()

    def __len__(self) -> int:
        return len(self._by_name)

    def __bool__(self) -> bool:
        return bool(self._by_name)

    def values(self) -> dict[str, int]:
        """Symbol -> forced value (raw bits), sorted by symbol (retain, trace)."""
        return {name: self._by_name[name].value for name in sorted(self._by_name)}

    def shown(self) -> dict[str, Shown]:
        """Symbol -> forced value as people read it (core/present.py; a bool as 0/1), sorted
        by symbol: status, the API, the page."""
        return {name: shown_number(f.type.value if f.type else None, f.value, f.scaling)
                for name, f in sorted(self._by_name.items())}

    def force(self, symbols: Mapping[str, Symbol], name: str, value: int,
              image: ProcessImage | None = None) -> Force:
        """Force `name` to `value`; `image` holds the program's current value (the shadow)."""
        sym = symbols.get(name)
        if sym is None:
            raise ForceRefused(f"no symbol {name!r} in the loaded program")
        entry = Force(name, sym.address.attr, sym.address.index, check_value(sym, value),
                      sym.type, sym.scaling)
        if not entry.is_input and name not in self.shadow:
            self.shadow[name] = 0 if image is None else int(getattr(image, entry.area)[entry.index])
        self._by_name[name] = entry
        self._split()
        return entry

    def release(self, name: str | None) -> list[tuple[Force, int | None]]:
        """Release one symbol (None: all): the released forces with their shadows (the
        program's own values, which the caller puts back). An unknown name is refused so
        that a typo does not look like success."""
        if name is None:
            names = sorted(self._by_name)
        elif name in self._by_name:
            names = [name]
        else:
            raise ForceRefused(f"symbol {name!r} is not forced")
        released = [(self._by_name.pop(n), self.shadow.pop(n, None)) for n in names]
        self._split()
        return released

    def rebind(self, symbols: Mapping[str, Symbol]) -> list[str]:
        """Re-resolve every force against a newly loaded program's symbols; drop (and return)
        those it does not declare, or declares with another type (the forced bits would mean
        another value there)."""
        kept: dict[str, Force] = {}
        dropped = []
        for name, old in sorted(self._by_name.items()):
            sym = symbols.get(name)
            try:
                if sym is None or sym.address.attr[0] != old.area[0] or \
                        old.type not in (None, sym.type):
                    raise ForceRefused(name)  # gone, now another direction or another type
                kept[name] = Force(name, sym.address.attr, sym.address.index,
                                   check_value(sym, old.value), sym.type, sym.scaling)
            except ForceRefused:
                dropped.append(name)
                self.shadow.pop(name, None)
        self._by_name = kept
        self._split()
        return dropped

    def restore(self, symbols: Mapping[str, Symbol],
                values: Iterable[tuple[str, int, int | None]]) -> None:
        """Replace every force by (name, value, shadow) triples (a warm restart); unusable
        ones are dropped."""
        self._by_name.clear()
        self.shadow.clear()
        for name, value, shadow in values:
            try:
                entry = self.force(symbols, name, int(value))
            except ForceRefused:
                continue
            if not entry.is_input:
                self.shadow[name] = int(shadow or 0)
        self._split()

    def triples(self) -> list[tuple[str, int, int | None]]:
        """(name, forced value, shadow) for every force, by name: what a retain keeps."""
        return [(n, f.value, self.shadow.get(n)) for n, f in sorted(self._by_name.items())]

    def _split(self) -> None:
        ordered = [self._by_name[n] for n in sorted(self._by_name)]
        self._inputs = tuple(f for f in ordered if f.is_input)
        self._outputs = tuple(f for f in ordered if not f.is_input)

    def apply_inputs(self, image: ProcessImage) -> None:
        """Step 2 of the scan: after the drivers' values are latched."""
        for f in self._inputs:
            _put(image, f)

    def unapply_outputs(self, image: ProcessImage) -> None:
        """Before a firing round: the program works on its own values of forced outputs."""
        for f in self._outputs:
            _put(image, Force(f.symbol, f.area, f.index, self.shadow.get(f.symbol, 0)))

    def apply_outputs(self, image: ProcessImage) -> None:
        """Step 4 of the scan: after the program's writes, before the drivers write."""
        for f in self._outputs:
            arr = getattr(image, f.area)
            self.shadow[f.symbol] = int(arr[f.index])
            _put(image, f)


def _put(image: ProcessImage, f: Force) -> None:
    arr = getattr(image, f.area)
    arr[f.index] = bool(f.value) if f.area.endswith("x") else f.value
