"""Modbus TCP application layer for the HMI slave: bytes in, bytes out.

Owns: MBAP framing, request validation in the order the Modbus spec prescribes (function ->
quantity/value -> address), function codes 1-6, 15, 16 and 23, exception responses.
Does not know: sockets, asyncio, pymodbus, how snapshots are published or writes applied.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from softplc.core.errors import SoftplcError
from softplc.core.modbus import (
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MAX_RW_READ_REGISTERS,
    MAX_RW_WRITE_REGISTERS,
    MAX_WRITE_BITS,
    MAX_WRITE_REGISTERS,
)
from softplc.core.snapshot import HmiWrite, SnapshotSource
from softplc.hmi.map import ExceptionCode, MapError, RegisterMap, Table

MBAP_SIZE = 7  # transaction id, protocol id, length, unit id
MIN_LENGTH = 2  # MBAP length field: unit id + function code at least
MAX_LENGTH = 254  # unit id + a PDU of at most 253 bytes (ADU <= 260)

COIL_ON, COIL_OFF = 0xFF00, 0x0000

Sink = Callable[[HmiWrite], None]


class FramingError(SoftplcError):
    """The byte stream cannot be split into ADUs any more: the connection must be closed."""


@dataclass(frozen=True, slots=True)
class Adu:
    transaction_id: int
    protocol_id: int
    unit_id: int
    pdu: bytes


def split_adu(buffer: bytes, start: int = 0) -> tuple[Adu | None, int]:
    """The ADU at `buffer[start:]` and the offset just after it, or (None, start) when more
    bytes are needed. Raises FramingError for an MBAP length no Modbus ADU can have."""
    if len(buffer) - start < MBAP_SIZE:
        return None, start
    tid, pid, length, unit = struct.unpack_from(">HHHB", buffer, start)
    if not MIN_LENGTH <= length <= MAX_LENGTH:
        raise FramingError(f"MBAP length {length} is not in {MIN_LENGTH}..{MAX_LENGTH}")
    end = start + 6 + length
    if len(buffer) < end:
        return None, start
    return Adu(tid, pid, unit, bytes(buffer[start + MBAP_SIZE : end])), end


def encode_adu(transaction_id: int, unit_id: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", transaction_id, 0, len(pdu) + 1, unit_id) + pdu


def exception_pdu(function_code: int, code: ExceptionCode) -> bytes:
    return bytes([(function_code | 0x80) & 0xFF, int(code)])


def _illegal_value(message: str) -> MapError:
    return MapError(ExceptionCode.ILLEGAL_DATA_VALUE, message)


def _fixed(body: bytes, fmt: str) -> tuple[int, ...]:
    if len(body) != struct.calcsize(fmt):
        raise _illegal_value(f"request data is {len(body)} bytes, expected {fmt}")
    return struct.unpack(fmt, body)


def _quantity(count: int, limit: int) -> None:
    if not 1 <= count <= limit:
        raise _illegal_value(f"quantity {count} is not in 1..{limit}")


def _payload(body: bytes, header: int, byte_count: int, expected: int) -> bytes:
    """The data after a `header`-byte header with its byte count, checked against both the
    quantity (`expected`) and the bytes actually present."""
    data = body[header:]
    if byte_count != expected or len(data) != byte_count:
        raise _illegal_value(f"byte count {byte_count}, expected {expected}, got {len(data)}")
    return data


def _pack_bits(bits: list[int]) -> bytes:
    packed = np.packbits(np.asarray(bits, dtype=np.uint8), bitorder="little").tobytes()
    return bytes([len(packed)]) + packed


def _unpack_bits(data: bytes, count: int) -> list[int]:
    bits = np.unpackbits(np.frombuffer(data, dtype=np.uint8), bitorder="little")
    return [int(b) for b in bits[:count]]


def _pack_registers(values: list[int]) -> bytes:
    return bytes([2 * len(values)]) + struct.pack(f">{len(values)}H", *values)


def _unpack_registers(data: bytes) -> list[int]:
    return list(struct.unpack(f">{len(data) // 2}H", data))


class Responder:
    """Answers one request PDU: reads from `source.latest()`, writes go to `sink` only after
    the whole request has been validated (all or nothing)."""

    def __init__(self, register_map: RegisterMap, source: SnapshotSource, sink: Sink) -> None:
        self._map = register_map
        self._source = source
        self._sink = sink
        self._handlers: dict[int, Callable[[bytes], bytes]] = {
            1: partial(self._read_bits, Table.COILS),
            2: partial(self._read_bits, Table.DISCRETE_INPUTS),
            3: partial(self._read_registers, Table.HOLDING_REGISTERS),
            4: partial(self._read_registers, Table.INPUT_REGISTERS),
            5: self._write_coil,
            6: self._write_register,
            15: self._write_coils,
            16: self._write_registers,
            23: self._read_write_registers,
        }

    @property
    def function_codes(self) -> tuple[int, ...]:
        return tuple(self._handlers)

    def answer(self, adu: Adu) -> bytes | None:
        """The response ADU, or None: a frame whose protocol id is not Modbus is dropped."""
        if adu.protocol_id != 0:
            return None
        return encode_adu(adu.transaction_id, adu.unit_id, self.answer_pdu(adu.pdu))

    def answer_pdu(self, pdu: bytes) -> bytes:
        function_code = pdu[0]
        handler = self._handlers.get(function_code)
        if handler is None:
            return exception_pdu(function_code, ExceptionCode.ILLEGAL_FUNCTION)
        try:
            return bytes([function_code]) + handler(pdu[1:])
        except MapError as exc:
            return exception_pdu(function_code, exc.code)

    def _journal(self, writes: list[HmiWrite]) -> None:
        for write in writes:
            self._sink(write)

    def _read_bits(self, table: Table, body: bytes) -> bytes:
        address, count = _fixed(body, ">HH")
        _quantity(count, MAX_READ_BITS)
        return _pack_bits(self._map.read(self._source.latest(), table, address, count))

    def _read_registers(self, table: Table, body: bytes) -> bytes:
        address, count = _fixed(body, ">HH")
        _quantity(count, MAX_READ_REGISTERS)
        return _pack_registers(self._map.read(self._source.latest(), table, address, count))

    def _write_coil(self, body: bytes) -> bytes:
        address, value = _fixed(body, ">HH")
        if value not in (COIL_ON, COIL_OFF):
            raise _illegal_value(f"coil value {value:#06x} is not 0xFF00 or 0x0000")
        self._journal(self._map.plan_write(Table.COILS, address, [int(value == COIL_ON)]))
        return body

    def _write_register(self, body: bytes) -> bytes:
        address, value = _fixed(body, ">HH")
        self._journal(self._map.plan_write(Table.HOLDING_REGISTERS, address, [value]))
        return body

    def _write_coils(self, body: bytes) -> bytes:
        address, count, byte_count = _fixed(body[:5], ">HHB")
        _quantity(count, MAX_WRITE_BITS)
        data = _payload(body, 5, byte_count, (count + 7) // 8)
        bits = _unpack_bits(data, count)
        self._journal(self._map.plan_write(Table.COILS, address, bits))
        return body[:4]

    def _write_registers(self, body: bytes) -> bytes:
        address, count, byte_count = _fixed(body[:5], ">HHB")
        _quantity(count, MAX_WRITE_REGISTERS)
        data = _payload(body, 5, byte_count, 2 * count)
        self._journal(
            self._map.plan_write(Table.HOLDING_REGISTERS, address, _unpack_registers(data))
        )
        return body[:4]

    def _read_write_registers(self, body: bytes) -> bytes:
        read_address, read_count, write_address, write_count, byte_count = _fixed(
            body[:9], ">HHHHB"
        )
        _quantity(read_count, MAX_RW_READ_REGISTERS)
        _quantity(write_count, MAX_RW_WRITE_REGISTERS)
        data = _payload(body, 9, byte_count, 2 * write_count)
        table = Table.HOLDING_REGISTERS
        writes = self._map.plan_write(table, write_address, _unpack_registers(data))
        # The spec performs the write before the read, but writes are journaled: the read
        # answers from the last published scan, which cannot contain this write yet.
        values = self._map.read(self._source.latest(), table, read_address, read_count)
        self._journal(writes)
        return _pack_registers(values)
