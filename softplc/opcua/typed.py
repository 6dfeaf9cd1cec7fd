"""Typed symbols over OPC UA (issue 30): DataTypes, the values nodes show and writes accept.

Owns: the OPC UA DataType of each symbol type (a scaled symbol: Double in engineering units),
the variant a symbol's raw bits show as (core/present.py `shown`, so OPC UA shows what the
API shows; a NaN or infinite real as that float), the raw bits a client's write gives
(`accepted`, the node's DataType exactly: BadTypeMismatch, BadOutOfRange), Part 8's
EUInformation (UNECE codes) and EURange of a scaled symbol, and the conversions of the
`kind: opcua` driver between a symbol's stored value and a remote variable's DataType.
Does not know: nodes, sessions, the channel.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from asyncua import ua

from softplc.core.datatypes import INFO, SymType, raw_of, value_of
from softplc.core.present import ValueRefused, accepted, scaling_of, shown, sym_type
from softplc.core.scaling import Scaling

VT = ua.VariantType
VARIANT_TYPES: Final = {SymType.BOOL: VT.Boolean, SymType.INT: VT.Int16,
                        SymType.WORD: VT.UInt16, SymType.DINT: VT.Int32,
                        SymType.UDINT: VT.UInt32, SymType.REAL: VT.Float,
                        SymType.LREAL: VT.Double}
SCALED: Final = VT.Double  # engineering values: the double the program reads
UNKNOWN: Final = VT.UInt64  # a type this version does not know: its raw bits, read-only
# present.py's text for what JSON cannot carry; OPC UA's Float and Double carry the number.
_NOT_FINITE: Final = {"NaN": math.nan, "Infinity": math.inf, "-Infinity": -math.inf}

# Part 8, 5.6.3: EUInformation of UNECE Recommendation 20 units; UnitId packs the common
# code's characters, 8 bits each.
UNECE_URI: Final = "http://www.opcfoundation.org/UA/units/un/cefact"
UNECE: Final = {"%": ("P1", "percent"), "°C": ("CEL", "degree Celsius"),
                "degC": ("CEL", "degree Celsius"), "l": ("LTR", "litre"), "bar": ("BAR", "bar"),
                "m": ("MTR", "metre")}


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why a client's write is not taken: the per-item status code and the log's text."""

    code: int
    text: str


@dataclass(frozen=True, slots=True)
class TypedSymbol:
    """How one symbol of the status board is shown and written over OPC UA."""

    type_name: str | None
    scale: Scaling | None
    vtype: ua.VariantType

    @classmethod
    def of(cls, entry: Mapping[str, Any]) -> TypedSymbol:
        """From the board's entry: `type` and, for a scaled symbol, `scale`."""
        type_name = entry.get("type")
        t = sym_type(type_name)
        scale = scaling_of(entry.get("scale"), type_name) if t is not SymType.BOOL else None
        vtype = UNKNOWN if t is None else SCALED if scale is not None else VARIANT_TYPES[t]
        return cls(type_name, scale, vtype)

    def variant(self, raw: int) -> ua.Variant:
        """The node's value for the raw bits `raw` of the symbol's location."""
        value = shown(self.type_name, raw, self.scale)
        if isinstance(value, str):
            return ua.Variant(_NOT_FINITE.get(value, math.nan), self.vtype)
        if self.vtype is SCALED or self.vtype is VT.Float:
            return ua.Variant(float(value), self.vtype)
        return ua.Variant(value, self.vtype)

    def written(self, name: str, variant: ua.Variant | None) -> int | Refusal:
        """The raw bits a client's write of `variant` stores: exactly the node's DataType
        (no conversions: an Int32 written to an Int16 node is refused like a Double written
        to a Boolean), then the symbol's type and scale (engineering units back to raw)."""
        if variant is None or variant.VariantType is not self.vtype or variant.is_array:
            got = "nothing" if variant is None else variant.VariantType.name
            return Refusal(ua.StatusCodes.BadTypeMismatch,
                           f"{name} is {self.vtype.name}, got {got}")
        try:
            return accepted(self.type_name, variant.Value, name, self.scale)
        except ValueRefused as exc:
            return Refusal(ua.StatusCodes.BadOutOfRange, str(exc))


def eu_information(unit: str) -> ua.EUInformation:
    """Part 8's EngineeringUnits of `unit`: its UNECE code when it is a common one, else
    UnitId -1 (none) with the text as DisplayName."""
    code, description = UNECE.get(unit, ("", unit))
    unit_id = -1
    if code:
        unit_id = 0
        for char in code:
            unit_id = unit_id << 8 | ord(char)
    return ua.EUInformation(NamespaceUri=UNECE_URI if code else None, UnitId=unit_id,
                            DisplayName=ua.LocalizedText(unit),
                            Description=ua.LocalizedText(description))


def eu_range(scale: Scaling) -> ua.Range:
    """Part 8's EURange: the engineering span, low to high (a span may run backwards)."""
    e0, e1 = scale.eng
    return ua.Range(Low=min(e0, e1), High=max(e0, e1))


# -- the `kind: opcua` driver: a symbol's stored value (raw, unscaled: drivers move raw
# values) to and from a remote variable of any numeric DataType ----------------------------

_INT_RANGES: Final = {VT.SByte: (-(1 << 7), (1 << 7) - 1), VT.Byte: (0, (1 << 8) - 1),
                      VT.Int16: (-(1 << 15), (1 << 15) - 1), VT.UInt16: (0, (1 << 16) - 1),
                      VT.Int32: (-(1 << 31), (1 << 31) - 1), VT.UInt32: (0, (1 << 32) - 1),
                      VT.Int64: (-(1 << 63), (1 << 63) - 1), VT.UInt64: (0, (1 << 64) - 1)}


def remote_raw(t: SymType, value: object) -> int:
    """The raw bits of a remote variable's `value` for a symbol of type `t`, or ValueError.
    Integers must fit (never wrapped; a whole float is taken); a real takes any number (a
    device may deliver NaN: kept, as the Modbus driver keeps the bits it reads)."""
    if t is SymType.BOOL:
        return int(bool(value))
    if isinstance(value, bool):
        value = int(value)
    if not isinstance(value, int | float):
        raise ValueError(f"{type(value).__name__} is not a number")
    info = INFO[t]
    if info.is_float:
        try:
            return raw_of(t, float(value))
        except OverflowError:
            raise ValueError(f"{value!r} is out of range of {t.value}") from None
    if isinstance(value, float) and not value.is_integer():
        raise ValueError(f"{value!r} is not a whole number ({t.value})")
    if not info.low <= int(value) <= info.high:
        raise ValueError(f"{value!r} is out of range of {t.value} ({info.low}..{info.high})")
    return raw_of(t, int(value))


def remote_variant(t: SymType, raw: int, vtype: ua.VariantType) -> ua.Variant:
    """The stored value of raw bits `raw` of type `t` as a remote variable of `vtype`, or
    ValueError when it does not fit (a fraction or a value out of the DataType's range)."""
    value = bool(raw) if t is SymType.BOOL else value_of(t, raw)
    if vtype is VT.Boolean:
        return ua.Variant(bool(value), vtype)
    if vtype in (VT.Float, VT.Double):
        if vtype is VT.Float and math.isfinite(value) and abs(value) > INFO[SymType.REAL].high:
            raise ValueError(f"{value!r} is out of range of Float")
        return ua.Variant(float(value), vtype)
    bounds = _INT_RANGES.get(vtype)
    if bounds is None:
        raise ValueError(f"the remote DataType {vtype.name} is not a number")
    if isinstance(value, float) and not value.is_integer():
        raise ValueError(f"{value!r} is not a whole number ({vtype.name})")
    if not bounds[0] <= int(value) <= bounds[1]:
        raise ValueError(f"{value!r} is out of range of {vtype.name}")
    return ua.Variant(int(value), vtype)
