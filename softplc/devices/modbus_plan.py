"""Modbus remote-I/O channels: parsing `TABLE:OFFSET` and planning one request per contiguous
range per table (pure: no socket, no thread).

Owns: Table, Channel, Block, IoPlan, parse_channel, plan_channels, channel_problems, the use of
the protocol's per-request quantity limits (core/modbus.py), and the register layout of 32-
and 64-bit symbols: 2 or 4 consecutive registers, in the device's `word_order`
(`join_words`, `split_words`), each value inside one request (docs/modbus.md).
Does not know: pymodbus, the I/O thread, the scan.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

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


class WordOrder(enum.Enum):
    """The order of a 32/64-bit value's registers on a remote device. BIG (the default) is
    the high word first, as our slave, OpenPLC and most devices; LITTLE is the low word first
    (some meters and drives: "word swap"). Bytes inside a register are always big-endian."""

    BIG = "big"
    LITTLE = "little"


_REGISTERS = {"W": 1, "D": 2, "L": 4}  # registers per value of an address width


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
    """One request per cycle: remote addresses start.. start+count-1. Value i occupies the
    `words` registers from start + i * words and is image index image_index[i] of the area
    the width gives (%IX/%IW/%ID/%IL for reads, %QX/%QW/%QD/%QL for writes): a 32/64-bit
    value is never split between two requests."""

    table: Table
    start: int
    image_index: tuple[int, ...]
    words: int = 1  # registers per value: 1 (a bit or a word), 2 (32-bit), 4 (64-bit)

    @property
    def count(self) -> int:
        """Coils, inputs or registers: the request's quantity."""
        return len(self.image_index) * self.words

    @property
    def area_width(self) -> str:
        """The image area's width letter: X, W, D or L."""
        return "X" if self.table.is_bit else {1: "W", 2: "D", 4: "L"}[self.words]

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
    groups: dict[tuple[Area, Table, int], list[tuple[int, int]]] = {}
    for (area, table, offset), sym in used.items():
        words = _REGISTERS.get(sym.address.width.value, 1)
        if sym.channel is not None and parse_channel(sym.channel).offset == offset:
            groups.setdefault((area, table, words), []).append((offset, sym.address.index))
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
    allowed = _ALLOWED.get((area, is_bit))
    if allowed is None:
        return (f"{sym.address} is memory, not I/O: expected an %IX/%IW input or %QX/%QW output "
                "(or %ID/%IL, %QD/%QL)")
    if ch.table not in allowed:
        role = "input" if area is Area.INPUT else "output"
        kind = "bit" if is_bit else _KIND[sym.address.width.value]
        names = " or ".join(t.value for t in allowed)
        return f"channel {sym.channel!r}: a {kind} {role} ({sym.address}) expects {names}"
    words = _REGISTERS.get(sym.address.width.value, 1)
    if ch.offset + words - 1 > MAX_OFFSET:
        return (f"channel {sym.channel!r}: a {_KIND[sym.address.width.value]} needs registers "
                f"{ch.offset}..{ch.offset + words - 1}, beyond {MAX_OFFSET}")
    keys = [(area, ch.table, ch.offset + i) for i in range(words)]  # every register it takes
    for key in keys:
        if key in used:
            where = "" if key[2] == ch.offset else f" (its register {ch.table.value}:{key[2]})"
            return (f"channel {sym.channel!r}{where} is already used by symbol "
                    f"{used[key].name!r}")
    used.update(dict.fromkeys(keys, sym))
    return None


_KIND = {"W": "word", "D": "32-bit value (2 registers)", "L": "64-bit value (4 registers)"}


def join_words(registers: npt.NDArray[Any], words: int,
               order: WordOrder) -> npt.NDArray[np.uint64]:
    """The raw values of consecutive groups of `words` registers (as read)."""
    regs = registers.astype(np.uint64).reshape(-1, words)
    if order is WordOrder.LITTLE:
        regs = regs[:, ::-1]
    values = np.zeros(len(regs), dtype=np.uint64)
    for i in range(words):
        values = (values << np.uint64(16)) | regs[:, i]
    return values


def split_words(values: npt.NDArray[Any], words: int,
                order: WordOrder) -> list[int]:
    """The registers of `values` (as written), `words` per value."""
    wide = values.astype(np.uint64)
    shifts = [np.uint64(16 * (words - 1 - i)) for i in range(words)]
    if order is WordOrder.LITTLE:
        shifts.reverse()
    regs = np.stack([(wide >> shift) & np.uint64(0xFFFF) for shift in shifts], axis=1)
    out: list[int] = regs.reshape(-1).tolist()
    return out


def _blocks(
    groups: Mapping[tuple[Area, Table, int], list[tuple[int, int]]],
    area: Area,
    limits: Mapping[Table, int],
) -> tuple[Block, ...]:
    out: list[Block] = []
    for (group_area, table, words), pairs in sorted(
            groups.items(), key=lambda kv: (kv[0][1].value, kv[0][2])):
        if group_area is not area:
            continue
        most = limits[table] // words  # values per request
        run: list[tuple[int, int]] = []
        for offset, index in sorted(pairs):
            if run and (offset != run[-1][0] + words or len(run) == most):
                out.append(Block(table, run[0][0], tuple(i for _, i in run), words))
                run = []
            run.append((offset, index))
        out.append(Block(table, run[0][0], tuple(i for _, i in run), words))
    return tuple(out)
