"""The Modbus reference for the fuzz tests, written from the spec (Modbus Application
Protocol V1.1b3, sections 6 and 7) and docs/modbus.md, not from softplc.hmi.frames.

`expected(pdu, image, status)` gives the exact response PDU for any request PDU: exception
01 for an unknown function, 03 for a bad quantity, byte count, length or coil value, 02 for
an address outside the table, otherwise the normal response.
"""

from __future__ import annotations

import struct

import numpy as np

from softplc.core.image import ProcessImage
from softplc.core.snapshot import Status
from softplc.hmi.map import status_registers

READ_LIMITS = {1: 2000, 2: 2000, 3: 125, 4: 125}
WRITE_LIMITS = {15: 1968, 16: 123}
RW_LIMITS = (125, 121)


class Refused(Exception):
    def __init__(self, code: int) -> None:
        self.code = code


Table = dict[int, int]  # Modbus address -> value; an address absent is outside the map
WHOLE: dict[int, int] = {}  # holding register -> the first register of its 32/64-bit value


def _wide(table: Table, start: int, values: list[int], registers: int) -> None:
    """32/64-bit values from `start`, high word first (docs/modbus.md, 32- and 64-bit)."""
    for n, value in enumerate(values):
        first = start + registers * n
        for k in range(registers):
            table[first + k] = value >> (16 * (registers - 1 - k)) & 0xFFFF
            WHOLE[first + k] = first


def _tables(image: ProcessImage, status: Status) -> dict[int, Table]:
    """Every readable table by read function code (docs/modbus.md, the map)."""
    listed = lambda *arrays: dict(enumerate(int(v) for a in arrays for v in list(a)))  # noqa: E731
    words = image.sizes.words
    holding = listed(image.qw, image.mw)
    inputs = listed(image.iw, status_registers(status))
    WHOLE.clear()
    for table, areas in ((holding, (("md", 2, 2), ("ml", 4, 4), ("qd", 8, 2), ("ql", 10, 4))),
                         (inputs, (("id", 2, 2), ("il", 4, 4)))):
        for area, at, registers in areas:
            _wide(table, at * words, [int(v) for v in getattr(image, area)], registers)
    return {1: listed(image.qx, image.mx), 2: listed(image.ix), 3: holding, 4: inputs}


def _check(ok: bool, code: int) -> None:
    if not ok:
        raise Refused(code)


def _range(table: Table, address: int, count: int) -> list[int]:
    _check(all(a in table for a in range(address, address + count)), 2)
    return [table[a] for a in range(address, address + count)]


def _whole(address: int, count: int) -> None:
    """A register write covers every register of each 32/64-bit value it touches."""
    end = address + count
    for a in (address, end - 1):
        if a in WHOLE:
            first = WHOLE[a]
            last = max(r for r, f in WHOLE.items() if f == first)
            _check(first >= address and last < end, 2)


def _read(fc: int, body: bytes, tables: dict[int, Table]) -> bytes:
    _check(len(body) == 4, 3)
    address, count = struct.unpack(">HH", body)
    _check(1 <= count <= READ_LIMITS[fc], 3)
    values = _range(tables[fc], address, count)
    if fc in (1, 2):
        packed = np.packbits(np.array(values, dtype=np.uint8), bitorder="little").tobytes()
        return bytes([fc, len(packed)]) + packed
    return bytes([fc, 2 * count]) + struct.pack(f">{count}H", *values)


def _write_single(fc: int, body: bytes, tables: dict[int, Table]) -> bytes:
    _check(len(body) == 4, 3)
    address, value = struct.unpack(">HH", body)
    if fc == 5:
        _check(value in (0xFF00, 0x0000), 3)
    _range(tables[1 if fc == 5 else 3], address, 1)
    if fc == 6:
        _whole(address, 1)
    return bytes([fc]) + body


def _write_multiple(fc: int, body: bytes, tables: dict[int, Table]) -> bytes:
    _check(len(body) >= 5, 3)
    address, count, byte_count = struct.unpack(">HHB", body[:5])
    _check(1 <= count <= WRITE_LIMITS[fc], 3)
    want = (count + 7) // 8 if fc == 15 else 2 * count
    _check(byte_count == want and len(body) - 5 == byte_count, 3)
    _range(tables[1 if fc == 15 else 3], address, count)
    if fc == 16:
        _whole(address, count)
    return bytes([fc]) + body[:4]


def _read_write(body: bytes, tables: dict[int, Table]) -> bytes:
    _check(len(body) >= 9, 3)
    r_address, r_count, w_address, w_count, byte_count = struct.unpack(">HHHHB", body[:9])
    _check(1 <= r_count <= RW_LIMITS[0] and 1 <= w_count <= RW_LIMITS[1], 3)
    _check(byte_count == 2 * w_count and len(body) - 9 == byte_count, 3)
    _range(tables[3], w_address, w_count)
    _whole(w_address, w_count)
    values = _range(tables[3], r_address, r_count)  # the last published scan (docs/modbus.md)
    return bytes([23, 2 * r_count]) + struct.pack(f">{r_count}H", *values)


def expected(pdu: bytes, image: ProcessImage, status: Status) -> bytes:
    fc, body = pdu[0], pdu[1:]
    tables = _tables(image, status)
    try:
        if fc in READ_LIMITS:
            return _read(fc, body, tables)
        if fc in (5, 6):
            return _write_single(fc, body, tables)
        if fc in WRITE_LIMITS:
            return _write_multiple(fc, body, tables)
        if fc == 23:
            return _read_write(body, tables)
        raise Refused(1)
    except Refused as refusal:
        return bytes([(fc | 0x80) & 0xFF, refusal.code])


def is_write(pdu: bytes, reply: bytes) -> bool:
    """A request whose normal response means something was journaled."""
    return pdu[0] in (5, 6, 15, 16, 23) and reply[0] == pdu[0]
