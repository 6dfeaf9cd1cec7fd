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


def _tables(image: ProcessImage, status: Status) -> dict[int, list[int]]:
    """Every readable table as a flat list, by read function code."""
    bits = lambda a: [int(v) for v in a.tolist()]  # noqa: E731
    return {
        1: bits(image.qx) + bits(image.mx),
        2: bits(image.ix),
        3: bits(image.qw) + bits(image.mw),
        4: bits(image.iw) + status_registers(status),
    }


def _check(ok: bool, code: int) -> None:
    if not ok:
        raise Refused(code)


def _range(table: list[int], address: int, count: int) -> list[int]:
    _check(address + count <= len(table), 2)
    return table[address : address + count]


def _read(fc: int, body: bytes, tables: dict[int, list[int]]) -> bytes:
    _check(len(body) == 4, 3)
    address, count = struct.unpack(">HH", body)
    _check(1 <= count <= READ_LIMITS[fc], 3)
    values = _range(tables[fc], address, count)
    if fc in (1, 2):
        packed = np.packbits(np.array(values, dtype=np.uint8), bitorder="little").tobytes()
        return bytes([fc, len(packed)]) + packed
    return bytes([fc, 2 * count]) + struct.pack(f">{count}H", *values)


def _write_single(fc: int, body: bytes, tables: dict[int, list[int]]) -> bytes:
    _check(len(body) == 4, 3)
    address, value = struct.unpack(">HH", body)
    if fc == 5:
        _check(value in (0xFF00, 0x0000), 3)
    _range(tables[1 if fc == 5 else 3], address, 1)
    return bytes([fc]) + body


def _write_multiple(fc: int, body: bytes, tables: dict[int, list[int]]) -> bytes:
    _check(len(body) >= 5, 3)
    address, count, byte_count = struct.unpack(">HHB", body[:5])
    _check(1 <= count <= WRITE_LIMITS[fc], 3)
    want = (count + 7) // 8 if fc == 15 else 2 * count
    _check(byte_count == want and len(body) - 5 == byte_count, 3)
    _range(tables[1 if fc == 15 else 3], address, count)
    return bytes([fc]) + body[:4]


def _read_write(body: bytes, tables: dict[int, list[int]]) -> bytes:
    _check(len(body) >= 9, 3)
    r_address, r_count, w_address, w_count, byte_count = struct.unpack(">HHHHB", body[:9])
    _check(1 <= r_count <= RW_LIMITS[0] and 1 <= w_count <= RW_LIMITS[1], 3)
    _check(byte_count == 2 * w_count and len(body) - 9 == byte_count, 3)
    _range(tables[3], w_address, w_count)
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
