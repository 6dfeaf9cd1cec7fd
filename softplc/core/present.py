"""What an operator or a client sees of a symbol's value, and what they may give it.

Owns: the one seam between the raw bits an image area stores and the values people and
clients read and write: `value` (what the program reads), `shown` (JSON: status board, API,
page, `softplc status`, `simulate`), `text` (a value with its unit at the precision its
scale resolves: `why`), `plotted` (a number for a waveform: the VCD) and `accepted` (HMI
writes and forces from the API and the CLI), with the refusal's text. Scaling (core/scaling.py)
is applied here too: a scaled symbol is shown and given in engineering units everywhere.
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


def value(type_name: str | None, raw: int,
          scale: Scaling | Mapping[str, Any] | None = None) -> bool | int | float:
    """What the raw bits `raw` of a symbol of type `type_name` hold as the program reads
    them: a bool, a signed or unsigned integer, a real (the shortest decimal that is the
    stored single, so 0.1 written is 0.1 read); with a scale, the engineering value (a
    double). NaN and infinities stay floats. An unknown type: the raw bits."""
    t = sym_type(type_name)
    if t is None:
        return int(raw)
    if t is SymType.BOOL:
        return bool(raw)
    number = value_of(t, int(raw))
    scaling = scaling_of(scale, type_name)
    if scaling is not None:
        return scaling.to_eng(number)
    if t is SymType.REAL and math.isfinite(number):
        return float(str(np.float32(number)))
    return number


def shown(type_name: str | None, raw: int,
          scale: Scaling | Mapping[str, Any] | None = None) -> Shown:
    """`value` for JSON: a NaN or an infinity as its text (NOT_FINITE)."""
    number = value(type_name, raw, scale)
    if isinstance(number, float) and not math.isfinite(number):
        return NOT_FINITE[repr(number)]
    return number


def decimals(scaling: Scaling) -> int | None:
    """The decimals that tell one raw count from the next in engineering units (the scale's
    resolution): 1 for raw -500..1500 = -50..150 (0.1 per count), 3 for 0..27648 = 0..100
    (0.0036 per count). None on a real raw type, which has no counts."""
    if not scaling.whole:
        return None
    (r0, r1), (e0, e1) = scaling.raw, scaling.eng
    step = abs((e1 - e0) / (r1 - r0))
    return max(0, math.ceil(-math.log10(step) - 1e-9))  # 1e-9: 0.1 is 1, not 2


def plotted(type_name: str | None, raw: int,
            scale: Scaling | Mapping[str, Any] | None = None) -> bool | int | float:
    """`value`, a scaled one rounded to its scale's resolution (`decimals`; a real raw type
    to 7 significant digits): the number a waveform or a text shows."""
    number = value(type_name, raw, scale)
    scaling = scaling_of(scale, type_name)
    if scaling is None or not math.isfinite(number):
        return number
    places = decimals(scaling)
    return round(number, places) if places is not None else float(f"{number:.7g}")


def text(type_name: str | None, number: bool | int | float,
         scale: Scaling | Mapping[str, Any] | None = None) -> str:
    """`number`, a value as the program reads it (a guard's operand: a scaled symbol's
    engineering value), as a person reads it: a bool as 0/1, an integer as it is, a real as
    the shortest decimal of its single, an lreal as its double, NaN and infinities as
    NOT_FINITE; a scaled value at its scale's resolution with its unit (`4.4 °C`)."""
    t = sym_type(type_name)
    scaling = scaling_of(scale, type_name)
    if isinstance(number, float) and not math.isfinite(number):
        out = NOT_FINITE[repr(number)]
    elif t is SymType.BOOL or isinstance(number, bool):
        out = str(int(number))
    elif scaling is not None:
        places = decimals(scaling)
        out = f"{number:.{places}f}" if places is not None else str(float(f"{number:.7g}"))
        out = out.lstrip("-") if float(out) == 0 else out  # no "-0.0"
    elif t is SymType.REAL:
        out = str(np.float32(number))
    else:
        out = repr(number)
    unit = scaling.unit if scaling is not None else ""
    return f"{out} {unit}" if unit else out


def raw_text(type_name: str | None, raw: int,
             scale: Scaling | Mapping[str, Any] | None = None) -> str:
    """The raw bits `raw` as `text` shows their value (a force, a board entry)."""
    return text(type_name, value(type_name, raw, scale), scale)


def shown_number(type_name: str | None, raw: int,
                 scale: Scaling | Mapping[str, Any] | None = None) -> Shown:
    """As `shown`, a bool as 0/1: the way forces are given and reported."""
    value = shown(type_name, raw, scale)
    return int(value) if isinstance(value, bool) else value


def shown_rounded(type_name: str | None, raw: int,
                  scale: Scaling | Mapping[str, Any] | None = None) -> Shown:
    """As `shown_number`, a scaled value at its scale's resolution (`plotted`): what a
    person reads in a list of changes (the timeline), not the double's noise."""
    number = plotted(type_name, raw, scale)
    if isinstance(number, float) and not math.isfinite(number):
        return NOT_FINITE[repr(number)]
    return int(number) if isinstance(number, bool) else number


def entry_form(type_name: str | None,
               scale: Scaling | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """How a page shows and takes a symbol's value: `scaled`, `unit` (a scaled symbol's),
    `range` (what an input box offers: a scaled symbol's engineering span, 0..100 %, not
    its raw type's -32768..32767; an integer type's range; None for a bool or a real) and
    `decimals` (a scaled value's display precision, `decimals`; None: as it comes)."""
    t = sym_type(type_name)
    scaling = scaling_of(scale, type_name)
    if scaling is not None and t is not SymType.BOOL:
        (e0, e1) = scaling.eng
        return {"scaled": True, "unit": scaling.unit, "range": [min(e0, e1), max(e0, e1)],
                "decimals": decimals(scaling)}
    whole = t is not None and t is not SymType.BOOL and not INFO[t].is_float
    return {"scaled": False, "unit": "",
            "range": [INFO[t].low, INFO[t].high] if whole and t else None, "decimals": None}


def text_of(entry: Mapping[str, Any], value: object) -> str:
    """`value` as JSON carries it for a status board entry (its `type` and `scale`), as
    `text` writes it: `47.002 %`. A text value (NaN, "released") as it is."""
    if isinstance(value, str) or not isinstance(value, bool | int | float):
        return str(value)
    return text(entry.get("type"), value, entry.get("scale"))


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
    except (TypeRangeError, TypeError, OverflowError):  # OverflowError: an int past a double
        raise refused from None


def _article(t: SymType) -> str:
    """'an int', 'an lreal' ('el-real'), 'a word', 'a dint', 'a udint' ('you-dint')."""
    return "an" if t in (SymType.INT, SymType.LREAL) else "a"


def _scaled(t: SymType, scaling: Scaling, value: object, symbol: str) -> int:
    (e0, e1), unit = scaling.eng, f" {scaling.unit}" if scaling.unit else ""
    refused = ValueRefused(
        f"symbol {symbol} is scaled ({min(e0, e1):g}..{max(e0, e1):g}{unit} "
        f"on {_article(t)} {t.value}): "
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
