"""The Sparkplug B payload on the wire: a small proto2 encoder and decoder of Eclipse Tahu's
`sparkplug_b.proto` (Payload, Metric, PropertySet, PropertyValue), the parts softplc sends
and reads (no DataSet, Template or extensions).

Owns: Metric and Payload values, the datatype numbers (spec 6.4.16), how a value goes on the
wire per datatype (Int8/16/32 sign-extended into the uint32 `int_value`, as Tahu Java and JS
read it; UInt32 in `int_value` as the spec says, read from `long_value` too), and decoding a
host's NCMD/DCMD with every malformed input a DecodeError (never another exception).
Does not know: MQTT, topics, symbols, sessions.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Final

from softplc.core.errors import SoftplcError

Value = bool | int | float | str | None

# Sparkplug B DataType enum (spec 6.4.16)
INT8, INT16, INT32, INT64 = 1, 2, 3, 4
UINT8, UINT16, UINT32, UINT64 = 5, 6, 7, 8
FLOAT, DOUBLE, BOOLEAN, STRING, DATETIME, TEXT = 9, 10, 11, 12, 13, 14
DATATYPE_NAMES: Final = {INT8: "Int8", INT16: "Int16", INT32: "Int32", INT64: "Int64",
                         UINT8: "UInt8", UINT16: "UInt16", UINT32: "UInt32", UINT64: "UInt64",
                         FLOAT: "Float", DOUBLE: "Double", BOOLEAN: "Boolean",
                         STRING: "String", DATETIME: "DateTime", TEXT: "Text"}
_INT_FIELD: Final = frozenset({INT8, INT16, INT32, UINT8, UINT16, UINT32})
_LONG_FIELD: Final = frozenset({INT64, UINT64, DATETIME})
_SIGNED: Final = {INT8: 8, INT16: 16, INT32: 32, INT64: 64}
_VARINT, _I64, _LEN, _I32 = 0, 1, 2, 5
MAX_METRICS: Final = 10_000  # in one decoded payload: a host's command is a handful


class DecodeError(SoftplcError, ValueError):
    """A payload that is not a Sparkplug B Payload softplc can read."""


@dataclass(frozen=True, slots=True)
class Metric:
    name: str | None
    datatype: int | None
    value: Value
    alias: int | None = None
    timestamp: int | None = None
    properties: tuple[tuple[str, int, Value], ...] = ()  # (key, datatype, value)
    typed: bool = True  # the datatype goes on the wire (not in DATA by alias: spec 6.4.6)


@dataclass(frozen=True, slots=True)
class Payload:
    timestamp: int | None
    metrics: tuple[Metric, ...] = ()
    seq: int | None = None
    uuid: str | None = None
    body: bytes | None = field(default=None)


# -- encoding ---------------------------------------------------------------------------------

def _varint(n: int) -> bytes:
    n &= (1 << 64) - 1
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _key(number: int, wire: int) -> bytes:
    return _varint(number << 3 | wire)


def _bytes(number: int, data: bytes) -> bytes:
    return _key(number, _LEN) + _varint(len(data)) + data


def _wire_value(datatype: int, value: Value, fields: tuple[int, int, int, int, int, int]
                ) -> bytes:
    """`value` in the oneof field its datatype uses; `fields` are the numbers of int, long,
    float, double, boolean and string in the message (Metric and PropertyValue differ)."""
    f_int, f_long, f_float, f_double, f_bool, f_string = fields
    if datatype == BOOLEAN:
        return _key(f_bool, _VARINT) + _varint(int(bool(value)))
    if datatype in _INT_FIELD:
        number = int(value or 0)
        return _key(f_int, _VARINT) + _varint(number & 0xFFFFFFFF)  # sign-extended to 32
    if datatype in _LONG_FIELD:
        return _key(f_long, _VARINT) + _varint(int(value or 0))
    if datatype == FLOAT:
        return _key(f_float, _I32) + struct.pack("<f", float(value or 0.0))
    if datatype == DOUBLE:
        return _key(f_double, _I64) + struct.pack("<d", float(value or 0.0))
    return _bytes(f_string, str(value if value is not None else "").encode())


def _properties(props: tuple[tuple[str, int, Value], ...]) -> bytes:
    keys = b"".join(_bytes(1, key.encode()) for key, _, _ in props)
    values = b"".join(
        _bytes(2, _key(1, _VARINT) + _varint(datatype)
               + (_key(2, _VARINT) + b"\x01" if value is None else
                  _wire_value(datatype, value, (3, 4, 5, 6, 7, 8))))
        for _, datatype, value in props)
    return keys + values


def encode_metric(metric: Metric) -> bytes:
    out = bytearray()
    if metric.name is not None:
        out += _bytes(1, metric.name.encode())
    if metric.alias is not None:
        out += _key(2, _VARINT) + _varint(metric.alias)
    if metric.timestamp is not None:
        out += _key(3, _VARINT) + _varint(metric.timestamp)
    if metric.datatype is not None and metric.typed:
        out += _key(4, _VARINT) + _varint(metric.datatype)
    if metric.properties:
        out += _bytes(9, _properties(metric.properties))
    if metric.value is None:
        out += _key(7, _VARINT) + b"\x01"  # is_null
    else:
        out += _wire_value(metric.datatype or STRING, metric.value, (10, 11, 12, 13, 14, 15))
    return bytes(out)


def encode(payload: Payload) -> bytes:
    out = bytearray()
    if payload.timestamp is not None:
        out += _key(1, _VARINT) + _varint(payload.timestamp)
    for metric in payload.metrics:
        out += _bytes(2, encode_metric(metric))
    if payload.seq is not None:
        out += _key(3, _VARINT) + _varint(payload.seq)
    if payload.uuid is not None:
        out += _bytes(4, payload.uuid.encode())
    if payload.body is not None:
        out += _bytes(5, payload.body)
    return bytes(out)


# -- decoding ---------------------------------------------------------------------------------

def _read_varint(data: bytes, at: int) -> tuple[int, int]:
    shift = result = 0
    while True:
        if at >= len(data) or shift > 63:
            raise DecodeError("a varint runs past the end of the payload")
        byte = data[at]
        at += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result & ((1 << 64) - 1), at
        shift += 7


def _fields(data: bytes) -> list[tuple[int, int, int | bytes]]:
    """(field number, wire type, value) of one message: a varint or fixed as an int, a
    length-delimited field as its bytes."""
    out: list[tuple[int, int, int | bytes]] = []
    at = 0
    while at < len(data):
        key, at = _read_varint(data, at)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise DecodeError("field number 0")
        if wire == _VARINT:
            value, at = _read_varint(data, at)
            out.append((number, wire, value))
        elif wire in (_I64, _I32):
            size = 8 if wire == _I64 else 4
            if at + size > len(data):
                raise DecodeError("a fixed-width field runs past the end")
            out.append((number, wire, int.from_bytes(data[at:at + size], "little")))
            at += size
        elif wire == _LEN:
            size, at = _read_varint(data, at)
            if at + size > len(data):
                raise DecodeError("a length-delimited field runs past the end")
            out.append((number, wire, data[at:at + size]))
            at += size
        else:
            raise DecodeError(f"wire type {wire} is not read here")
    return out


def _text(raw: int | bytes) -> str:
    if not isinstance(raw, bytes):
        raise DecodeError("a string field is not length-delimited")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise DecodeError("a string is not UTF-8") from None


def signed(datatype: int | None, raw: int) -> int:
    """The number of a signed datatype's wire bits `raw` (the small ints sign-extended in
    32 bits); other datatypes unchanged."""
    bits = _SIGNED.get(datatype or 0)
    if bits is None:
        return raw
    width = 32 if bits < 64 else 64  # the small ints come sign-extended in 32 bits
    raw &= (1 << width) - 1
    return raw - (1 << width) if raw >> (width - 1) else raw


def _value(datatype: int | None, number: int, wire: int, raw: int | bytes,
           names: tuple[int, int, int, int, int, int]) -> Value:
    f_int, f_long, f_float, f_double, f_bool, f_string = names
    if number in (f_int, f_long) and isinstance(raw, int):
        return signed(datatype, raw)
    if number == f_float and wire == _I32 and isinstance(raw, int):
        return float(struct.unpack("<f", raw.to_bytes(4, "little"))[0])
    if number == f_double and wire == _I64 and isinstance(raw, int):
        return float(struct.unpack("<d", raw.to_bytes(8, "little"))[0])
    if number == f_bool and isinstance(raw, int):
        return bool(raw)
    if number == f_string:
        return _text(raw)
    raise DecodeError(f"value field {number} with wire type {wire} is not read here")


def decode_metric(data: bytes) -> Metric:
    name: str | None = None
    alias = timestamp = datatype = None
    value: Value = None
    found: tuple[int, int, int | bytes] | None = None
    for number, wire, raw in _fields(data):
        if number == 1:
            name = _text(raw)
        elif number in (2, 3, 4) and isinstance(raw, int):
            alias, timestamp, datatype = (raw, timestamp, datatype) if number == 2 else \
                (alias, raw, datatype) if number == 3 else (alias, timestamp, raw)
        elif 10 <= number <= 15:
            found = (number, wire, raw)
    if found is not None:
        value = _value(datatype, *found, (10, 11, 12, 13, 14, 15))
    return Metric(name, datatype, value, alias, timestamp)


def decode(data: bytes) -> Payload:
    """The Payload in `data`; DecodeError for anything that is not one."""
    timestamp = seq = None
    metrics: list[Metric] = []
    for number, _, raw in _fields(data):
        if number == 1 and isinstance(raw, int):
            timestamp = raw
        elif number == 2 and isinstance(raw, bytes):
            if len(metrics) >= MAX_METRICS:
                raise DecodeError(f"more than {MAX_METRICS} metrics")
            metrics.append(decode_metric(raw))
        elif number == 3 and isinstance(raw, int):
            seq = raw
    return Payload(timestamp, tuple(metrics), seq)
