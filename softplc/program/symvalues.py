"""The values a symbol of a symbols file declares: `scale:`, `safe:`, `init:` and `finite:`.

Owns: checking each against the symbol's type and scale and converting it once, when the
file is parsed (a `safe:` or `init:` of a scaled symbol is in engineering units and kept as
the raw value it stores); every problem reported at its key's line.
Does not know: the file's structure (program/io_image.py), the scan, when an `init:` applies
(core/memory.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from softplc.core.datatypes import INFO, stored
from softplc.core.present import ValueRefused, accepted
from softplc.core.scaling import Scaling
from softplc.core.symbols import Direction, SymType
from softplc.program.suggest import did_you_mean, did_you_mean_key
from softplc.program.yamlload import line_of, trap_hint

Report = Callable[[int, str, str], None]  # (line, YAML path, message): the reader's problem()

SCALE_KEYS = ("raw", "eng", "unit", "clamp", "modbus")
SCALE_FORM = "{raw: [0, 27648], eng: [0.0, 100.0], unit: '%', clamp: true}"
MODBUS_SHOWS = ("raw", "eng")


def scale(spec: dict[Any, Any], path: str, sym_type: SymType, report: Report) -> Scaling | None:
    """`scale:` (core/scaling.py); None when absent or bad (each problem reported)."""
    if "scale" not in spec:
        return None
    value, line, path = spec["scale"], line_of(spec, "scale"), f"{path}.scale"
    if sym_type is SymType.BOOL:
        report(line, path, "a bool cannot be scaled: scale applies to int, word, dint, udint, "
                           "real and lreal symbols")
        return None
    if not isinstance(value, dict) or "raw" not in value or "eng" not in value:
        report(line, path, f"expected {SCALE_FORM} (raw and eng required)")
        return None
    bad = 0

    def counted(line: int, where: str, message: str) -> None:
        nonlocal bad
        bad += 1
        report(line, where, message)

    for key in sorted(set(value) - set(SCALE_KEYS), key=str):
        counted(line_of(value, key), f"{path}.{key}", f"unknown key {key!r}"
                f"{did_you_mean_key(str(key), SCALE_KEYS)}; expected one of "
                f"{', '.join(SCALE_KEYS)}")
    raw = _span(value, "raw", path, sym_type, counted)
    eng = _span(value, "eng", path, None, counted)
    unit, clamp = value.get("unit", ""), value.get("clamp", False)
    modbus = value.get("modbus", "raw")
    if not isinstance(unit, str):
        counted(line_of(value, "unit"), f"{path}.unit",
                f"unit must be text (e.g. '%' or 'degC'), got {unit!r}")
    if not isinstance(clamp, bool):
        counted(line_of(value, "clamp"), f"{path}.clamp",
                f"clamp must be true or false{trap_hint(clamp)}")
    if not isinstance(modbus, str) or modbus not in MODBUS_SHOWS:
        hint = did_you_mean(modbus, MODBUS_SHOWS) if isinstance(modbus, str) else ""
        counted(line_of(value, "modbus"), f"{path}.modbus",
                f"modbus {modbus!r}: expected raw (the Modbus slave serves the raw value, the "
                f"default) or eng (the engineering value, in the symbol's type){hint}")
    if raw is None or eng is None or bad:
        return None
    return Scaling(raw, (float(eng[0]), float(eng[1])), str(unit), bool(clamp),
                   whole=not INFO[sym_type].is_float, modbus=str(modbus))


def _span(scale: dict[Any, Any], key: str, path: str, sym_type: SymType | None,
          report: Report) -> tuple[int | float, int | float] | None:
    """`raw: [low, high]` in `sym_type`'s range (None: `eng`, any finite numbers), the two
    ends different: a span of zero has no inverse."""
    value, line, path = scale.get(key), line_of(scale, key), f"{path}.{key}"
    if (not isinstance(value, list) or len(value) != 2
            or not all(_is_number(v) and math.isfinite(v) for v in value)):
        report(line, path, f"{key} must be two numbers [from, to], got {value!r}")
        return None
    if sym_type is not None and not all(INFO[sym_type].low <= v <= INFO[sym_type].high
                                        for v in value):
        info = INFO[sym_type]
        report(line, path, f"raw {value} is out of range of {sym_type.value} "
                           f"({info.low}..{info.high})")
        return None
    if value[0] == value[1]:
        report(line, path, f"{key} span is zero ({value[0]} to {value[1]}): a scale needs two "
                           "different ends")
        return None
    return value[0], value[1]


def safe(spec: dict[Any, Any], path: str, sym_type: SymType, scaling: Scaling | None,
         report: Report) -> int | float:
    value = spec.get("safe", 0)
    line = line_of(spec, "safe")
    if scaling is not None and sym_type is not SymType.BOOL:
        try:  # in engineering units, kept as the raw value it stores
            return stored(sym_type, scaling.to_raw(value))
        except (TypeError, ArithmeticError) as exc:
            report(line, f"{path}.safe", "safe value of a scaled symbol must be a number in "
                   f"engineering units that scales to a raw {sym_type.value} ({exc})"
                   f"{trap_hint(value)}")
            return 0
    if sym_type is SymType.BOOL:
        if isinstance(value, bool) or value in (0, 1):
            return int(value)
        report(line, f"{path}.safe", f"safe value of a bool must be true or false"
                                     f"{trap_hint(value)}")
        return 0
    info = INFO[sym_type]
    if not isinstance(value, bool) and isinstance(value, int | float):
        try:
            return stored(sym_type, value)
        except (TypeError, ArithmeticError):
            pass
    what = "a number" if info.is_float else f"a whole number {info.low}..{info.high}"
    report(line, f"{path}.safe",
           f"safe value of {article(sym_type.value)} must be {what}{trap_hint(value)}")
    return 0


_NOT_MEMORY = {
    Direction.IN: "an input's value comes from its driver at every scan",
    Direction.OUT: "an output's value is the program's while it runs and its `safe:` value "
                   "otherwise",
}


def init(spec: dict[Any, Any], name: str, path: str, sym_type: SymType, direction: Direction,
         scaling: Scaling | None, report: Report) -> int | None:
    """`init:` of a memory symbol as the raw bits it puts there, checked as an operator's
    write of the same value is (core/present.py `accepted`: the type's range, a scaled
    symbol's value in engineering units); None when absent or bad (reported)."""
    if "init" not in spec:
        return None
    value, line, path = spec["init"], line_of(spec, "init"), f"{path}.init"
    if direction is not Direction.MEMORY:
        report(line, path, f"init applies to memory symbols (%M) only, not {direction.value}: "
                           f"{_NOT_MEMORY[direction]}")
        return None
    if scaling is not None and scaling.clamp and _is_number(value) \
            and not min(scaling.eng) <= value <= max(scaling.eng):
        report(line, path, f"init {value!r} is outside the scale's eng span "
                           f"[{scaling.eng[0]:g}, {scaling.eng[1]:g}] (clamp: true would store "
                           "its end instead)")
        return None
    try:
        return accepted(sym_type.value, value, name, scaling)
    except ValueRefused as exc:
        report(line, path, f"init {value!r} refused: {exc}{trap_hint(value)}")
        return None


def finite(spec: dict[Any, Any], path: str, sym_type: SymType, report: Report) -> bool:
    """`finite:` (default true): whether a Modbus register write of a NaN's or an infinity's
    bits is refused (core/nonfinite.py); real and lreal symbols only."""
    if "finite" not in spec:
        return True
    value, line = spec["finite"], line_of(spec, "finite")
    if not isinstance(value, bool):
        report(line, f"{path}.finite", f"finite must be true or false{trap_hint(value)}")
        return True
    if not INFO[sym_type].is_float:
        report(line, f"{path}.finite", f"finite applies to real and lreal symbols, not "
                                       f"{article(sym_type.value)}: no other type holds NaN")
        return True
    return value


def article(word: str) -> str:
    return f"{'an' if word[0] in 'aeiou' else 'a'} {word}"


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
