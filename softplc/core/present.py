"""What an operator or a client sees of a symbol's value, and what they may give it.

Owns: the one seam between the raw bits an image area stores and the values people and
clients read and write: `shown` (status board, API, page, `softplc status`, `simulate`) and
`accepted` (HMI writes and forces from the API and the CLI), with the refusal's text.
Does not know: HTTP, addresses, the scan. Scaling (raw counts to engineering units) will sit
here too, so that every typed read and write goes through these two functions.
"""

from __future__ import annotations

import json
import math

import numpy as np

from softplc.core.datatypes import INFO, SymType, TypeRangeError, raw_of, stored, value_of
from softplc.core.errors import SoftplcError

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


def shown(type_name: str | None, raw: int) -> Shown:
    """The value of the raw bits `raw` of a symbol of type `type_name`: a bool, a signed or
    unsigned integer, or a real (the shortest decimal that is the stored single, so 0.1
    written is 0.1 read). An unknown type shows the raw bits."""
    t = sym_type(type_name)
    if t is None:
        return int(raw)
    if t is SymType.BOOL:
        return bool(raw)
    value = value_of(t, int(raw))
    if isinstance(value, float):
        if not math.isfinite(value):
            return NOT_FINITE[repr(value)]
        if t is SymType.REAL:
            return float(str(np.float32(value)))
    return value


def shown_number(type_name: str | None, raw: int) -> Shown:
    """As `shown`, a bool as 0/1: the way forces are given and reported."""
    value = shown(type_name, raw)
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


def accepted(type_name: str | None, value: object, symbol: str) -> int:
    """The raw bits that store `value` (a JSON value: bool, int or float) in `symbol` of type
    `type_name`, or ValueRefused. A whole float is taken for an integer type (JSON's 3.0);
    a real is rounded to single precision (nearest, ties to even), as a program's write is."""
    t = sym_type(type_name)
    if t is None:
        raise ValueRefused(f"symbol {symbol} has the unknown type {type_name!r}")
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


def _text(value: object) -> str:
    try:
        return json.dumps(value)[:40]
    except (TypeError, ValueError):
        return repr(value)[:40]
