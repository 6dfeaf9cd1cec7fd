"""Modbus remote-I/O channels: parsing `TABLE:OFFSET` and planning one request per contiguous
range per table (pure: no socket, no thread).

Owns: Table, Channel, Block, IoPlan, parse_channel, plan_channels, channel_problems and the
use of the protocol's per-request quantity limits (core/modbus.py).
Does not know: pymodbus, the I/O thread, the scan.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from softplc.core.image import Area
from softplc.core.modbus import (
    MAX_ADDRESS,
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_WRITE_BITS,
    MAX_WRITE_REGISTERS,
)
from softplc.core.symbols import Symbol

MAX_OFFSET = MAX_ADDRESS


class Table(enum.Enum):
    COIL = "coil"
    DI = "di"
    HR = "hr"
    IR = "ir"

    @property
    def is_bit(self) -> bool:
        return self in (Table.COIL, Table.DI)


# Per-request quantity limits of the Modbus application protocol (FC 1/2, 3/4, 15, 16).
_READ_LIMIT = {Table.COIL: MAX_READ_BITS, Table.DI: MAX_READ_BITS,
               Table.HR: MAX_READ_REGISTERS, Table.IR: MAX_READ_REGISTERS}
_WRITE_LIMIT = {Table.COIL: MAX_WRITE_BITS, Table.HR: MAX_WRITE_REGISTERS}
# Where an image location may come from (inputs) or go to (outputs), keyed (area, is_bit).
_ALLOWED = {
    (Area.INPUT, True): (Table.DI, Table.COIL),
    (Area.INPUT, False): (Table.IR, Table.HR),
    (Area.OUTPUT, True): (Table.COIL,),
    (Area.OUTPUT, False): (Table.HR,),
}


@dataclass(frozen=True, slots=True)
class Channel:
    table: Table
    offset: int


def parse_channel(text: str) -> Channel:
    """`di:3` -> Channel(DI, 3). Offsets are 0-based PDU addresses."""
    table_text, sep, offset_text = text.strip().partition(":")
    if not sep:
        raise ValueError(f"channel {text!r}: expected TABLE:OFFSET, e.g. di:0")
    try:
        table = Table(table_text.strip().lower())
    except ValueError:
        raise ValueError(
            f"channel {text!r}: table {table_text!r} is not coil, di, hr or ir"
        ) from None
    try:
        offset = int(offset_text.strip())
    except ValueError:
        raise ValueError(f"channel {text!r}: offset {offset_text!r} is not an integer") from None
    if not 0 <= offset <= MAX_OFFSET:
        raise ValueError(f"channel {text!r}: offset {offset} is not in 0..{MAX_OFFSET}")
    return Channel(table, offset)


@dataclass(frozen=True, slots=True)
class Block:
    """One request per cycle: remote addresses start.. start+count-1, where remote address
    start+i maps to image index image_index[i] (of %IX/%IW for reads, %QX/%QW for writes)."""

    table: Table
    start: int
    image_index: tuple[int, ...]

    @property
    def count(self) -> int:
        return len(self.image_index)

    def __str__(self) -> str:
        return f"{self.table.value}:{self.start}+{self.count}"


@dataclass(frozen=True, slots=True)
class IoPlan:
    reads: tuple[Block, ...]
    writes: tuple[Block, ...]


def plan_channels(symbols: Iterable[Symbol]) -> IoPlan:
    """Validate every symbol's channel and group them into contiguous ranges per table.

    Raises one ValueError listing every problem, each naming the symbol and what was expected.
    """
    used: dict[tuple[Area, Table, int], Symbol] = {}
    issues = [f"symbol {sym.name!r} (line {sym.line}): {issue}"
              for sym, issue in channel_problems(symbols, used)]
    if issues:
        raise ValueError("modbus channels:\n  " + "\n  ".join(issues))
    groups: dict[tuple[Area, Table], list[tuple[int, int]]] = {}
    for (area, table, offset), sym in used.items():
        groups.setdefault((area, table), []).append((offset, sym.address.index))
    return IoPlan(
        _blocks(groups, Area.INPUT, _READ_LIMIT), _blocks(groups, Area.OUTPUT, _WRITE_LIMIT)
    )


def channel_problems(symbols: Iterable[Symbol],
                     used: dict[tuple[Area, Table, int], Symbol] | None = None
                     ) -> list[tuple[Symbol, str]]:
    """Every symbol whose channel this driver would refuse, with why (`softplc check` reports
    them without opening anything). `used` collects the valid channels, for planning."""
    used = {} if used is None else used
    found = ((sym, _check_symbol(sym, used)) for sym in symbols)
    return [(sym, issue) for sym, issue in found if issue]


def _check_symbol(sym: Symbol, used: dict[tuple[Area, Table, int], Symbol]) -> str | None:
    if sym.channel is None:
        return "no channel: expected TABLE:OFFSET with TABLE coil, di, hr or ir"
    try:
        ch = parse_channel(sym.channel)
    except ValueError as exc:
        return str(exc)
    area, is_bit = sym.address.area, sym.address.is_bit
    if sym.address.width.value in ("D", "L"):  # docs/modbus.md, 32- and 64-bit values
        return f"{sym.address}: 32/64-bit symbols on a Modbus driver are not supported yet"
    allowed = _ALLOWED.get((area, is_bit))
    if allowed is None:
        return f"{sym.address} is memory, not I/O: expected an %IX/%IW input or %QX/%QW output"
    if ch.table not in allowed:
        role = "input" if area is Area.INPUT else "output"
        kind = "bit" if is_bit else "word"
        names = " or ".join(t.value for t in allowed)
        return f"channel {sym.channel!r}: a {kind} {role} ({sym.address}) expects {names}"
    key = (area, ch.table, ch.offset)
    if key in used:
        return f"channel {sym.channel!r} is already used by symbol {used[key].name!r}"
    used[key] = sym
    return None


def _blocks(
    groups: Mapping[tuple[Area, Table], list[tuple[int, int]]],
    area: Area,
    limits: Mapping[Table, int],
) -> tuple[Block, ...]:
    out: list[Block] = []
    for (group_area, table), pairs in sorted(groups.items(), key=lambda kv: kv[0][1].value):
        if group_area is not area:
            continue
        run: list[tuple[int, int]] = []
        for offset, index in sorted(pairs):
            if run and (offset != run[-1][0] + 1 or len(run) == limits[table]):
                out.append(Block(table, run[0][0], tuple(i for _, i in run)))
                run = []
            run.append((offset, index))
        out.append(Block(table, run[0][0], tuple(i for _, i in run)))
    return tuple(out)
