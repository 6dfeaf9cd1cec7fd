"""The compile-time type rules of writes to symbols (docs/programs.md, types).

Owns: what a Moore output's constant value and an action's expression may write to a symbol
of each type. Does not know: the run-time checks (core/datatypes.py `stored`), YAML.
"""

from __future__ import annotations

from softplc.core.datatypes import range_text, whole_in_range
from softplc.core.expr import Compiled
from softplc.core.symbols import Symbol, SymType


def output_problem(sym: Symbol, value: object) -> str | None:
    """The problem of a Moore output's value (written as it is, every scan), or None."""
    if sym.type is SymType.BOOL:
        if value in (0, 1, True, False):
            return None
        return f"{sym.name} is a bool; its output value must be true or false"
    if whole_in_range(sym.type, value):
        return None
    return f"{sym.name} is a {sym.type.value}; its output value must be {range_text(sym.type)}"


def real_to_integer(sym: Symbol, value: Compiled) -> str | None:
    """The problem of writing `value` (a Compiled: its static `kind`) to `sym`: a real to an
    integer symbol needs an explicit conversion (docs/programs.md, types), else None."""
    if value.kind != "float" or sym.type in (SymType.REAL, SymType.LREAL):
        return None
    return (f"{sym.name} is {sym.type.value}: {value.text!r} gives a real; convert it "
            f"({sym.type.value}(x) rounds half to even, trunc(x) cuts toward zero)")
