"""Scaled symbols served in engineering units by the Modbus slave (`scale: {..., modbus: eng}`;
docs/modbus.md, scaled symbols).

Owns: which registers carry an engineering value (EngTable, read from the status board's
symbol entries); turning a location's raw bits into the register bits an HMI reads, and an
HMI's register bits back into raw bits, both through core/present.py (`shown`, `accepted`:
the one seam between raw bits and the values people give and read); following downloads
(EngSource: the running program's table, taken from the board once it describes it).
Does not know: sockets, frames, the map's layout, the runtime's processes.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any, Final

import numpy as np

from softplc.core.datatypes import INFO, SymType, raw_of, value_of
from softplc.core.image import WORD_MAX, AddressError, Area, Width, parse_address
from softplc.core.present import accepted, shown
from softplc.core.snapshot import SnapshotSource

RECHECK_S: Final = 0.001  # the board is read at most this often while it lags the snapshot


@dataclass(frozen=True, slots=True)
class EngSymbol:
    """A scaled symbol whose registers carry its engineering value, in its own type."""

    name: str
    type: SymType
    scale: Mapping[str, Any]  # the board's form of its scaling (Scaling.as_dict)

    def register(self, raw: int) -> int:
        """The bits an HMI reads for the location's `raw` bits: the engineering value as the
        symbol's type holds it; an integer rounded to the nearest (ties to even, as every
        conversion) and held to the type's range, a real the nearest single (an infinity
        beyond it), an lreal the double. A read cannot be refused: it is clamped."""
        value = float(shown(self.type.value, raw, self.scale))  # "NaN", "Infinity": floats
        info = INFO[self.type]
        if self.type is SymType.LREAL:
            return raw_of(self.type, value)
        if self.type is SymType.REAL:
            with np.errstate(over="ignore"):
                return raw_of(self.type, float(np.float32(value)))
        if math.isnan(value):
            return 0
        whole = round(value) if math.isfinite(value) else (info.high if value > 0 else info.low)
        return raw_of(self.type, min(max(whole, info.low), info.high))

    def raw(self, register: int) -> int:
        """The raw bits an HMI's write of `register` (the bits of an engineering value in the
        symbol's type) stores, converted as a write through the HTTP API is; ValueRefused
        when the value cannot be stored (the slave answers 03)."""
        return accepted(self.type.value, value_of(self.type, register), self.name, self.scale)


@dataclass(frozen=True, slots=True)
class EngTable:
    """The registers a program's symbols present in engineering units, by IEC area and index.
    `stale`: the snapshot already runs another program than this table's (just after a
    download, until the board describes it)."""

    program_hash: str = ""
    areas: Mapping[tuple[Area, Width], Mapping[int, EngSymbol]] = field(
        default_factory=lambda: MappingProxyType({}))
    stale: bool = False
    # The real and lreal symbols served raw that refuse NaN and infinities (core/nonfinite.py:
    # all but those declared `finite: false`): (name, type) by IEC area and index.
    floats: Mapping[tuple[Area, Width], Mapping[int, tuple[str, SymType]]] = field(
        default_factory=lambda: MappingProxyType({}))

    def area(self, area: Area, width: Width) -> Mapping[int, EngSymbol]:
        return self.areas.get((area, width), _NONE)

    def finite(self, area: Area, width: Width) -> Mapping[int, tuple[str, SymType]]:
        return self.floats.get((area, width), _NO_FLOATS)


_NONE: Mapping[int, EngSymbol] = MappingProxyType({})
_NO_FLOATS: Mapping[int, tuple[str, SymType]] = MappingProxyType({})
NO_ENG = EngTable()


def table_of(document: Mapping[str, Any]) -> EngTable:
    """The EngTable of a status board document (runtime/statusdoc.py): its symbols whose
    `scale` says `modbus: eng`."""
    areas: dict[tuple[Area, Width], dict[int, EngSymbol]] = {}
    floats: dict[tuple[Area, Width], dict[int, tuple[str, SymType]]] = {}
    for name, entry in (document.get("symbols") or {}).items():
        scale = entry.get("scale") if isinstance(entry, dict) else None
        eng = isinstance(scale, dict) and scale.get("modbus") == "eng"
        try:
            address, sym_type = parse_address(str(entry.get("address"))), SymType(entry["type"])
        except (AddressError, ValueError, KeyError, TypeError, AttributeError):
            continue
        where = (address.area, address.width)
        if eng and isinstance(scale, dict) and sym_type is not SymType.BOOL:
            areas.setdefault(where, {})[address.index] = EngSymbol(
                str(name), sym_type, MappingProxyType(dict(scale)))
        elif INFO[sym_type].is_float and entry.get("finite", True) is True:
            floats.setdefault(where, {})[address.index] = (str(name), sym_type)
    return EngTable(str(document.get("program_hash") or ""), MappingProxyType(
        {key: MappingProxyType(symbols) for key, symbols in areas.items()}),
        floats=MappingProxyType({key: MappingProxyType(f) for key, f in floats.items()}))


def join_registers(registers: tuple[int, ...]) -> int:
    """One value's registers, most significant first (the map's word order), as its bits."""
    raw = 0
    for register in registers:
        raw = (raw << 16) | (register & WORD_MAX)
    return raw


Presentation = Callable[[str | None], EngTable]
"""The table for a program hash (None: the program the latest snapshot runs)."""


class EngSource:
    """The Presentation of a runtime: the table of the running program, from the status board
    (`read_board`; the scan process publishes a new program's board before the first
    snapshot that runs it, then about every 50 ms) once the board describes the program the
    snapshot runs. Until then the last table read is served, marked stale: reads use it,
    register writes are refused (map.py)."""

    def __init__(self, read_board: Callable[[], dict[str, Any]],
                 source: SnapshotSource) -> None:
        self._read_board = read_board
        self._source = source
        self._table = NO_ENG
        self._checked_s = float("-inf")

    def __call__(self, program_hash: str | None = None) -> EngTable:
        running = (self._source.latest().status.program_hash if program_hash is None
                   else program_hash)
        if running == self._table.program_hash:
            return self._table
        now_s = time.monotonic()
        if now_s - self._checked_s >= RECHECK_S:
            self._checked_s = now_s
            self._table = self._read(running)
        table = self._table
        return table if table.program_hash == running else replace(table, stale=True)

    def _read(self, running: str) -> EngTable:
        """The running program's table if the board describes it, else the last one."""
        if not running:  # no program: nothing is presented
            return NO_ENG
        document = self._read_board()
        return table_of(document) if document.get("program_hash") == running else self._table
