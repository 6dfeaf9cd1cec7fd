"""The compile-time type rules of writes to symbols (docs/programs.md, types).

Owns: what a Moore output's constant value and an action's expression may write to a symbol
of each type. Does not know: the run-time checks (core/datatypes.py `stored`), YAML.
"""

from __future__ import annotations

from softplc.core.datatypes import range_text, stored, whole_in_range
from softplc.core.expr import Compiled
from softplc.core.symbols import Symbol, SymType


def output_problem(sym: Symbol, value: object) -> str | None:
    """The problem of a Moore output's value (written as it is, every scan), or None."""
    if sym.type is SymType.BOOL:
        if value in (0, 1, True, False):
            return None
        return f"{sym.name} is a bool; its output value must be true or false"
    if sym.scaling is not None:
        return _scaled_output_problem(sym, value)
    if whole_in_range(sym.type, value):
        return None
    return f"{sym.name} is a {sym.type.value}; its output value must be {range_text(sym.type)}"


def real_to_integer(sym: Symbol, value: Compiled) -> str | None:
    """The problem of writing `value` (a Compiled: its static `kind`) to `sym`: a real to an
    integer symbol needs an explicit conversion (docs/programs.md, types), else None."""
    if value.kind != "float" or sym.type in (SymType.REAL, SymType.LREAL) or sym.scaling:
        return None
    return (f"{sym.name} is {sym.type.value}: {value.text!r} gives a real; convert it "
            f"({sym.type.value}(x) rounds half to even, trunc(x) cuts toward zero)")


def _scaled_output_problem(sym: Symbol, value: object) -> str | None:
    """A scaled symbol's Moore value is in engineering units, and so is its value while no
    place drives it (0): both must scale to a raw value its type holds."""
    assert sym.scaling is not None
    for eng in (value, 0):
        try:
            stored(sym.type, sym.scaling.to_raw(eng))
        except (TypeError, ArithmeticError) as exc:
            unit = f" {sym.scaling.unit}" if sym.scaling.unit else ""
            return (f"{sym.name} is scaled ({sym.type.value}, engineering units{unit}): its "
                    f"output value {eng!r} does not scale to a raw value ({exc})")
    return None
