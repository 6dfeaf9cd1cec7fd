"""Numbers in the expression language: arithmetic over integers and floats, and conversions.

Owns: the operators' run-time rules (integers exact and bounded by 2**63, floats IEEE 754
double, NaN and infinities never produced silently, division by zero an error), the callable
conversions (`int(x)`, `real(x)`, `trunc(x)`, ...) and a static guess of what kind of number
an expression gives, so that a fraction written to an integer symbol is refused at compile
time. Does not know: the syntax tree's compiler (core/expr.py), symbols' storage.

Every failure raises an ArithmeticError or a TypeError: a guard or action that raises is a
located diagnostic (docs/programs.md), never a crash and never a silent value.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable

from softplc.core.datatypes import SymType, TypeRangeError, convert, trunc

INT_LIMIT = 1 << 63  # results beyond +-2**63 are an error: no unbounded integer growth

Num = int | float


def as_number(value: object) -> Num:
    """An operand of arithmetic: integers (bools as 0/1) and floats, nothing else."""
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int | float):
        return value
    if isinstance(value, str):
        raise TypeError("text cannot take part in arithmetic")
    raise TypeError(f"{type(value).__name__} {value!r} cannot take part in arithmetic")


def checked(value: Num) -> Num:
    """A result: integers within +-2**63, floats finite."""
    if isinstance(value, float):
        if math.isnan(value):
            raise TypeRangeError("the result is NaN")
        if math.isinf(value):
            raise TypeRangeError("the result is infinite (overflow)")
        return value
    if not -INT_LIMIT < value < INT_LIMIT:
        raise OverflowError("integer result out of range")
    return value


def _nonzero(b: Num, what: str) -> None:
    # Division by zero is a run-time error of the guard or action (docs/programs.md): the
    # engine makes it a located diagnostic (guard false, action skipped), never a crash.
    if b == 0:
        raise ZeroDivisionError(f"{what} by zero")


def _floordiv(a: Num, b: Num) -> Num:
    _nonzero(b, "integer division" if isinstance(a, int) and isinstance(b, int) else "division")
    return a // b


def _mod(a: Num, b: Num) -> Num:
    _nonzero(b, "integer modulo" if isinstance(a, int) and isinstance(b, int) else "modulo")
    return a % b


def _truediv(a: Num, b: Num) -> float:
    _nonzero(b, "division")
    return a / b


def _bitwise(fn: Callable[[int, int], int]) -> Callable[[Num, Num], int]:
    def op(a: Num, b: Num) -> int:
        if isinstance(a, float) or isinstance(b, float):
            raise TypeError("& | ^ take integers, not reals")
        return fn(a, b)
    return op


BINOPS: dict[type[ast.operator], Callable[[Num, Num], Num]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: _truediv,
    ast.FloorDiv: _floordiv,
    ast.Mod: _mod,
    ast.BitAnd: _bitwise(operator.and_),
    ast.BitOr: _bitwise(operator.or_),
    ast.BitXor: _bitwise(operator.xor),
}

def _conversion(t: SymType) -> Callable[[object], Num]:
    return lambda value: convert(t, value)


CONVERSIONS: dict[str, Callable[[object], Num]] = {
    t.value: _conversion(t) for t in SymType if t is not SymType.BOOL
}
CONVERSIONS["trunc"] = trunc
_FLOAT_CALLS = frozenset({"real", "lreal"})

# -- static kinds: "int", "float", "bool", "text" or "any" (unknown until run time) ----------


def _join(a: str, b: str) -> str:
    if a == b:
        return a
    if {a, b} <= {"int", "bool"}:
        return "int"
    return "any"


def _arith(a: str, b: str) -> str:
    if "float" in (a, b) and {a, b} <= {"float", "int", "bool"}:
        return "float"
    if {a, b} <= {"int", "bool"}:
        return "int"
    return "any"


def static_kind(node: ast.AST, names: Callable[[str], str]) -> str:
    """What an expression gives, as far as its text tells; `names` gives a name's kind."""
    if isinstance(node, ast.Constant):
        value = node.value
        return {bool: "bool", int: "int", float: "float", str: "text"}.get(type(value), "any")
    if isinstance(node, ast.Name):
        return names(node.id)
    if isinstance(node, ast.BinOp):
        if isinstance(node.op, ast.Div):
            return "float"
        return _arith(static_kind(node.left, names), static_kind(node.right, names))
    if isinstance(node, ast.UnaryOp):
        return "bool" if isinstance(node.op, ast.Not) else static_kind(node.operand, names)
    if isinstance(node, ast.Compare | ast.BoolOp):
        return "bool"
    if isinstance(node, ast.IfExp):
        return _join(static_kind(node.body, names), static_kind(node.orelse, names))
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
        name = node.func.id
        if name in _FLOAT_CALLS:
            return "float"
        if name in CONVERSIONS:
            return "int"
        if name in ("rising", "falling"):
            return "bool"
        kinds = [static_kind(a, names) for a in node.args]
        out = kinds[0] if kinds else "any"
        for kind in kinds[1:]:
            out = _arith(out, kind)
        return out
    return "any"
