"""The elementary data types of symbols (IEC 61131-3 names) and their storage in the image.

Owns: SymType (bool, int, word, dint, udint, real, lreal), which address width holds each
type, ranges, and the codec between a value and the raw unsigned bits an image area stores
(`raw_of`, `value_of`), with the rules of a write to a typed symbol (`stored`) and of the
explicit conversions of the expression language (`convert`).
Does not know: addresses' parsing, YAML, the scan.

Storage: every area holds raw bits (uint16 words, uint32 double words, uint64 long words);
the symbol's type says how to read them: `int` is the two's complement of a word, `real`
the IEEE 754 single in a double word, `lreal` the double in a long word. So the image, the
snapshot, the trace and retain move bits, never values, and nothing is lost on the way.
"""

from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass

import numpy as np

from softplc.core.errors import SoftplcError

Number = int | float


class SymType(enum.Enum):
    BOOL = "bool"
    INT = "int"  # IEC INT: signed 16-bit
    WORD = "word"  # IEC UINT/WORD: unsigned 16-bit
    DINT = "dint"  # signed 32-bit
    UDINT = "udint"  # unsigned 32-bit
    REAL = "real"  # IEEE 754 single
    LREAL = "lreal"  # IEEE 754 double


TYPE_NAMES = tuple(t.value for t in SymType)


@dataclass(frozen=True, slots=True)
class TypeInfo:
    width: str  # the address width letter that holds it: X, W, D, L
    bits: int
    low: Number
    high: Number
    is_float: bool = False


_F32_MAX = float(np.finfo(np.float32).max)
INFO: dict[SymType, TypeInfo] = {
    SymType.BOOL: TypeInfo("X", 1, 0, 1),
    SymType.INT: TypeInfo("W", 16, -(1 << 15), (1 << 15) - 1),
    SymType.WORD: TypeInfo("W", 16, 0, (1 << 16) - 1),
    SymType.DINT: TypeInfo("D", 32, -(1 << 31), (1 << 31) - 1),
    SymType.UDINT: TypeInfo("D", 32, 0, (1 << 32) - 1),
    SymType.REAL: TypeInfo("D", 32, -_F32_MAX, _F32_MAX, True),
    SymType.LREAL: TypeInfo("L", 64, -math.inf, math.inf, True),
}
# The type a width holds when `type:` is not given: the one it held before types existed.
NATURAL = {"X": SymType.BOOL, "W": SymType.WORD, "D": SymType.DINT, "L": SymType.LREAL}


class TypeRangeError(SoftplcError, ArithmeticError):
    """A value its target type cannot hold: out of range, NaN, infinite, or a fraction for an
    integer type. An ArithmeticError, so a guard or action reports it as a diagnostic."""


def fits(t: SymType, width: str) -> bool:
    return INFO[t].width == width


def types_for(width: str) -> tuple[str, ...]:
    return tuple(t.value for t, info in INFO.items() if info.width == width)


def whole_in_range(t: SymType, value: object) -> bool:
    """A whole number `t` holds (a Moore output's value: written as it is, every scan)."""
    if not isinstance(value, int) or isinstance(value, bool):
        return False
    return INFO[t].low <= value <= INFO[t].high


def range_text(t: SymType) -> str:
    info = INFO[t]
    if info.is_float:
        return "a whole number"
    return f"{info.low}..{info.high}"


def _finite(value: float, what: str) -> float:
    if math.isnan(value):
        raise TypeRangeError(f"{what} is NaN")
    if math.isinf(value):
        raise TypeRangeError(f"{what} is infinite")
    return value


def _checked_int(t: SymType, value: int) -> int:
    info = INFO[t]
    if not info.low <= value <= info.high:
        raise TypeRangeError(f"{value} is out of range of {t.value} ({info.low}..{info.high})")
    return value


def to_real(value: float) -> float:
    """`value` rounded to the nearest IEEE 754 single (ties to even), as a Python float."""
    with np.errstate(over="ignore"):  # beyond the single range: inf, refused below
        single = float(np.float32(value))
    if math.isinf(single) and not math.isinf(value):
        raise TypeRangeError(f"{value!r} is out of range of real (|x| <= {_F32_MAX:.7g})")
    return single


def stored(t: SymType, value: object) -> Number:
    """The value a write of `value` to a symbol of type `t` stores, or TypeRangeError /
    TypeError. Integers must fit (never wrapped); a fraction is never written to an integer
    symbol without a conversion; NaN and infinities are never stored; a real is rounded to
    single precision here, so every later read sees exactly what the image holds."""
    if isinstance(value, str):
        raise TypeError("text cannot be written to a symbol")
    if t is SymType.BOOL:
        return 1 if value else 0
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float):
        _finite(value, "the result")
        if not INFO[t].is_float:
            raise TypeError(f"the fraction {value!r} cannot be written to a {t.value} symbol "
                            f"without a conversion: write {t.value}(...) or trunc(...)")
        return to_real(value) if t is SymType.REAL else value
    if not isinstance(value, int):
        raise TypeError(f"{type(value).__name__} cannot be written to a {t.value} symbol")
    if INFO[t].is_float:
        return to_real(float(value)) if t is SymType.REAL else float(value)
    return _checked_int(t, value)


def convert(t: SymType, value: object) -> Number:
    """The explicit conversion `t(value)` of an expression (`int(x)`, `real(x)`, ...). A float
    becomes an integer by rounding to the nearest, ties to even (IEC 61131-3's REAL_TO_INT
    rounds; ties to even is IEEE 754's default, Python's round()); out of range, NaN or
    infinite is an error, never a wrapped value."""
    if isinstance(value, str):
        raise TypeError("text cannot be converted to a number")
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, float) and not INFO[t].is_float:
        value = round(_finite(value, "the value"))
    return stored(t, value)


def trunc(value: object) -> int:
    """Towards zero (IEC TRUNC); NaN and infinities are errors."""
    if isinstance(value, str):
        raise TypeError("text cannot be converted to a number")
    if isinstance(value, float):
        return math.trunc(_finite(value, "the value"))
    if isinstance(value, int):
        return int(value)
    raise TypeError(f"{type(value).__name__} cannot be converted to a number")


def raw_of(t: SymType, value: Number) -> int:
    """The unsigned bits that hold `value` (already `stored`) in its area."""
    if t is SymType.REAL:
        return int(struct.unpack("<I", struct.pack("<f", value))[0])
    if t is SymType.LREAL:
        return int(struct.unpack("<Q", struct.pack("<d", value))[0])
    return int(value) & ((1 << INFO[t].bits) - 1)


def value_of(t: SymType, raw: int) -> Number:
    """What the raw bits of a location mean as a value of type `t`."""
    if t is SymType.REAL:
        return float(struct.unpack("<f", struct.pack("<I", raw & 0xFFFFFFFF))[0])
    if t is SymType.LREAL:
        return float(struct.unpack("<d", struct.pack("<Q", raw & (1 << 64) - 1))[0])
    if t is SymType.INT or t is SymType.DINT:
        bits = INFO[t].bits
        return raw - (1 << bits) if raw >> (bits - 1) & 1 else raw
    return raw
