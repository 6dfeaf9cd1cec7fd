"""What an operator or a client sees of a symbol's value, and what they may give it.

Owns: the one seam between the raw bits an image area stores and the values people and
clients read and write: `shown` (status board, API, page, `softplc status`, `simulate`) and
`accepted` (HMI writes and forces from the API and the CLI), with the refusal's text.
Scaling (raw counts to engineering units, core/scaling.py) is applied here too: a scaled
symbol is shown and given in engineering units, wherever it is read or written.
Does not know: HTTP, addresses, the scan.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from softplc.core.datatypes import INFO, SymType, TypeRangeError, raw_of, stored, value_of
from softplc.core.errors import SoftplcError
from softplc.core.scaling import Scaling

# JSON carries no NaN or infinity (a browser's JSON.parse refuses Python's `NaN`): a real
# that holds one is shown as this text, never as a number it does not hold.
Shown = bool | int | float | str
NOT_FINITE = {"nan": "NaN", "inf": "Infinity", "-inf": "-Infinity"}


class ValueRefused(SoftplcError, ValueError):
    """A value a symbol's type cannot take: wrong kind, a fraction for an integer, out of
    range, NaN or infinite. The text names the symbol, its type and what it takes."""


def sym_type(type_name: str | None) -> SymType | None:
    try:
        return SymType(type_name)
    except ValueError:
        return None


def scaling_of(scale: Scaling | Mapping[str, Any] | None, type_name: str | None
               ) -> Scaling | None:
    """A symbol's scaling, from the Symbol's or the status board's form (`as_dict`)."""
    if scale is None or isinstance(scale, Scaling):
        return scale
    t = sym_type(type_name)
    try:
        raw, eng = scale["raw"], scale["eng"]
        return Scaling((raw[0], raw[1]), (float(eng[0]), float(eng[1])),
                       str(scale.get("unit", "")), bool(scale.get("clamp", False)),
                       whole=t is None or not INFO[t].is_float)
    except (KeyError, TypeError, ValueError, IndexError):
        return None  # not a scale this version knows: shown unscaled, as the bits' type


def shown(type_name: str | None, raw: int,
          scale: Scaling | Mapping[str, Any] | None = None) -> Shown:
    """The value of the raw bits `raw` of a symbol of type `type_name`: a bool, a signed or
    unsigned integer, or a real (the shortest decimal that is the stored single, so 0.1
    written is 0.1 read); with a scale, the engineering value (a double, as the program
    reads it). An unknown type shows the raw bits."""
    t = sym_type(type_name)
    if t is None:
        return int(raw)
    if t is SymType.BOOL:
        return bool(raw)
    value = value_of(t, int(raw))
    scaling = scaling_of(scale, type_name)
    if scaling is not None:
        value = scaling.to_eng(value)
        return value if math.isfinite(value) else NOT_FINITE[repr(value)]
    if isinstance(value, float):
        if not math.isfinite(value):
            return NOT_FINITE[repr(value)]
        if t is SymType.REAL:
            return float(str(np.float32(value)))
    return value


def shown_number(type_name: str | None, raw: int,
                 scale: Scaling | Mapping[str, Any] | None = None) -> Shown:
    """As `shown`, a bool as 0/1: the way forces are given and reported."""
    value = shown(type_name, raw, scale)
    return int(value) if isinstance(value, bool) else value


def takes(t: SymType) -> str:
    """What a symbol of type `t` takes, for a refusal."""
    info = INFO[t]
    if t is SymType.BOOL:
        return "true/false or 0/1"
    if t is SymType.REAL:
        return f"a finite number, |x| <= {info.high:.7g}"
    if info.is_float:
        return "a finite number"
    return f"a whole number {info.low}..{info.high}"


def accepted(type_name: str | None, value: object, symbol: str,
             scale: Scaling | Mapping[str, Any] | None = None) -> int:
    """The raw bits that store `value` (a JSON value: bool, int or float) in `symbol` of type
    `type_name`, or ValueRefused. A whole float is taken for an integer type (JSON's 3.0);
    a real is rounded to single precision (nearest, ties to even), as a program's write is.
    With a scale, `value` is in engineering units and is scaled back to raw as a program's
    write is (clamped or refused by the scale's rule)."""
    t = sym_type(type_name)
    if t is None:
        raise ValueRefused(f"symbol {symbol} has the unknown type {type_name!r}")
    scaling = scaling_of(scale, type_name)
    if scaling is not None and t is not SymType.BOOL:
        return _scaled(t, scaling, value, symbol)
    article = "an" if t in (SymType.INT, SymType.LREAL) else "a"
    refused = ValueRefused(f"symbol {symbol} is {article} {t.value}: the value must be "
                           f"{takes(t)}, not {_text(value)}")
    if t is SymType.BOOL:
        if isinstance(value, bool) or (type(value) is int and value in (0, 1)):
            return int(value)
        raise refused
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise refused
    if isinstance(value, float) and value.is_integer() and not INFO[t].is_float:
        value = int(value)
    try:
        return raw_of(t, stored(t, value))
    except (TypeRangeError, TypeError):
        raise refused from None


def _scaled(t: SymType, scaling: Scaling, value: object, symbol: str) -> int:
    (e0, e1), unit = scaling.eng, f" {scaling.unit}" if scaling.unit else ""
    refused = ValueRefused(
        f"symbol {symbol} is scaled ({min(e0, e1):g}..{max(e0, e1):g}{unit} on a {t.value}): "
        f"the value must be a finite number in engineering units that scales into the "
        f"{t.value}'s range, not {_text(value)}")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise refused
    try:
        return raw_of(t, stored(t, scaling.to_raw(value)))
    except (TypeRangeError, TypeError, ValueError, OverflowError):
        raise refused from None


def _text(value: object) -> str:
    try:
        return json.dumps(value)[:40]
    except (TypeError, ValueError):
        return repr(value)[:40]
