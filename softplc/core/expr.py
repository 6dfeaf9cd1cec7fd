"""Sandboxed expression language for guards, actions and arc inscriptions.

Owns: parsing a program's expression text with Python's `ast`, checking every node against an
allowlist, resolving names against a scope, and compiling the tree into plain closures.
Does not know: YAML, files, devices. Program text never reaches eval/exec/compile: the only
thing that runs is the closure tree built here from the allowlisted node types.
"""

from __future__ import annotations

import ast
import enum
import math
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from softplc.core.arith import BINOPS, CONVERSIONS, INT_LIMIT, as_number, checked, static_kind
from softplc.core.datatypes import SymType
from softplc.core.errors import SoftplcError
from softplc.core.iecwords import XOR_HINT, rewrite, unrewrite

Value = int | bool | str | float
Thunk = Callable[["EvalContext"], Value]

__all__ = ["INT_LIMIT", "Compiled", "EvalContext", "ExprError", "NameKind", "Scope", "Value",
           "compile_expr", "name_kind", "names_in", "parse", "substitute"]

MAX_NODES = 400
MAX_TEXT = 2000
MAX_STR = 256  # characters of a text value (core/values.py MAX_TEXT: the same language)


class ExprError(SoftplcError, ValueError):
    """An expression that is not in the language. The message names what is wrong (the name,
    operator or constant), and the problem that reports it quotes the expression: a column
    would add nothing there (issue 43), so none is kept."""

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class NameKind(enum.Enum):
    BOOL = "bool"  # a bool symbol (input, output or memory bit)
    WORD = "word"  # an integer symbol: int, word, dint, udint
    REAL = "real"  # a floating-point symbol: real, lreal
    EVENT = "event"  # an event: true in the scan where it occurred
    TOKEN = "token"  # a token variable bound by an input arc
    CONST = "const"  # a subnet parameter bound to a literal


class EvalContext(Protocol):
    """What a compiled expression reads at run time. The scan supplies it."""

    def symbol(self, name: str) -> int | float: ...

    def previous(self, name: str) -> int | float: ...

    def event(self, name: str) -> bool: ...

    def token(self, var: str) -> Mapping[str, Value]: ...


class NoValues:
    """The EvalContext of what reads nothing (a constant, a net without guards): a symbol,
    its previous value or a token read is a KeyError; no event is present."""

    def symbol(self, name: str) -> int:
        raise KeyError(name)

    def previous(self, name: str) -> int:
        raise KeyError(name)

    def event(self, name: str) -> bool:
        return False

    def token(self, var: str) -> Mapping[str, Value]:
        raise KeyError(var)


@dataclass(frozen=True, slots=True)
class Scope:
    """Names an expression may use. `consts` are substituted literally (subnet parameters)."""

    names: Mapping[str, NameKind]
    consts: Mapping[str, Value] = field(default_factory=dict)
    token_fields: Mapping[str, frozenset[str]] | None = None  # None: any field allowed


@dataclass(frozen=True, slots=True)
class Compiled:
    """A compiled expression: call `fn(ctx)`. `reads` lists the symbols and events it reads,
    `edges` the symbols it takes edges of, so the scan knows when to re-evaluate it."""

    text: str
    fn: Thunk = field(compare=False)  # the same text in the same names: the same expression
    reads: frozenset[str]
    edges: frozenset[str]
    tokens: frozenset[str]
    # What it gives as far as its text tells (core/arith.py static_kind): "int", "float",
    # "bool", "text" or "any"; a "float" written to an integer symbol is refused.
    kind: str = field(default="any", compare=False)
    # What it was compiled in: a net crossing to another process compiles its expressions
    # again from text and scope (program/wire.py), never ships the closures.
    scope: Scope | None = field(default=None, compare=False, repr=False)

    def __call__(self, ctx: EvalContext) -> Value:
        return self.fn(ctx)


_CMPOPS: dict[type[ast.cmpop], Callable[[Any, Any], bool]] = {
    ast.Eq: operator.eq,
    ast.NotEq: operator.ne,
    ast.Lt: operator.lt,
    ast.LtE: operator.le,
    ast.Gt: operator.gt,
    ast.GtE: operator.ge,
}
_FUNCS: dict[str, int] = {"rising": 1, "falling": 1, "abs": 1, "min": 2, "max": 2,
                          **dict.fromkeys(CONVERSIONS, 1)}
_CONSTS: dict[str, Value] = {"true": True, "false": False, "TRUE": True, "FALSE": False}


class _Compiler:
    def __init__(self, text: str, scope: Scope, iec: frozenset[str] = frozenset()) -> None:
        self.text = text
        self.scope = scope
        self.iec = iec  # the IEC words the text used (core/iecwords.py)
        self.kind = _kinds(scope)
        self.reads: set[str] = set()
        self.edges: set[str] = set()
        self.tokens: set[str] = set()

    def build(self, node: ast.AST) -> Thunk:
        method: Callable[[Any], Thunk] | None = getattr(self, "on_" + type(node).__name__, None)
        if method is None:
            raise ExprError(f"{_describe(node)} is not allowed in an expression")
        return method(node)

    def on_Constant(self, node: ast.Constant) -> Thunk:
        value = node.value
        if isinstance(value, float):
            if not math.isfinite(value):
                raise ExprError(f"constant {value!r} is not a finite number")
            return lambda ctx: value
        if isinstance(value, bool | int | str) and not isinstance(value, bytes):
            if isinstance(value, int) and not isinstance(value, bool) and not (
                    -INT_LIMIT < value < INT_LIMIT):
                raise ExprError(f"integer {value} is out of range (at most 2**63 - 1)")
            if isinstance(value, str) and len(value) > MAX_STR:
                raise ExprError(f"text of {len(value)} characters (at most {MAX_STR})")
            return lambda ctx: value
        raise ExprError(f"constant {value!r} is not allowed: "
                              "use numbers, true/false or 'text'")

    def on_Name(self, node: ast.Name) -> Thunk:
        name = node.id
        if name.startswith("_"):
            raise ExprError(f"name {name!r} is not allowed (no leading underscore)")
        if name in self.scope.consts:
            const = self.scope.consts[name]
            return lambda ctx: const
        kind = self.scope.names.get(name)
        if kind is None:
            if name in _CONSTS:
                literal = _CONSTS[name]
                return lambda ctx: literal
            raise ExprError(f"unknown name {name!r}: not a symbol, event or token variable")
        if kind is NameKind.TOKEN:
            raise ExprError(f"token variable {name!r} needs a field, e.g. {name}.id")
        self.reads.add(name)
        if kind is NameKind.EVENT:
            return lambda ctx: ctx.event(name)
        if kind is NameKind.BOOL:
            return lambda ctx: bool(ctx.symbol(name))
        return lambda ctx: ctx.symbol(name)

    def on_Attribute(self, node: ast.Attribute) -> Thunk:
        base = node.value
        if not isinstance(base, ast.Name) or self.scope.names.get(base.id) is not NameKind.TOKEN:
            raise ExprError("attribute access is only allowed as <token variable>.<field>")
        var, attr = base.id, node.attr
        if attr.startswith("_"):
            raise ExprError(f"field {attr!r} is not allowed (no leading underscore)")
        allowed = (self.scope.token_fields or {}).get(var)
        if self.scope.token_fields is not None and allowed is not None and attr not in allowed:
            raise ExprError(f"token variable {var!r} has no field {attr!r}")
        self.tokens.add(var)

        def field_of(ctx: EvalContext) -> Value:
            record = ctx.token(var)
            if attr not in record:
                raise KeyError(f"token bound to {var!r} has no field {attr!r}")
            return record[attr]

        return field_of

    def _bool_operand(self, node: ast.expr, word: str) -> None:
        """IEC's AND/OR/NOT of integers are bitwise: only bools get the logical meaning."""
        kind = static_kind(node, self.kind)
        if kind not in ("bool", "any"):
            raise ExprError(f"{word} of {ast.unparse(node)!r} ({kind}): IEC's {word} of an "
                            f"integer is bitwise, here {word} is logical and takes bools; "
                            f"compare instead, e.g. {ast.unparse(node)} <> 0")

    def on_BoolOp(self, node: ast.BoolOp) -> Thunk:
        if self.iec & {"AND", "OR"}:
            for value in node.values:
                self._bool_operand(value, "AND" if isinstance(node.op, ast.And) else "OR")
        parts = [self.build(v) for v in node.values]
        if isinstance(node.op, ast.And):
            return lambda ctx: all(p(ctx) for p in parts)
        return lambda ctx: any(p(ctx) for p in parts)

    def on_UnaryOp(self, node: ast.UnaryOp) -> Thunk:
        inner = self.build(node.operand)
        if isinstance(node.op, ast.Not):
            return lambda ctx: not inner(ctx)
        if isinstance(node.op, ast.USub):
            return lambda ctx: checked(-as_number(inner(ctx)))
        if isinstance(node.op, ast.UAdd):
            return lambda ctx: as_number(inner(ctx))
        if "NOT" in self.iec:  # NOT was read as ~: IEC's precedence, logical on bools
            self._bool_operand(node.operand, "NOT")
            return lambda ctx: not inner(ctx)
        raise ExprError("operator ~ is not allowed; use 'not' or arithmetic")

    def on_BinOp(self, node: ast.BinOp) -> Thunk:
        op = _iec_mod if isinstance(node.op, ast.MatMult) and "MOD" in self.iec else (
            BINOPS.get(type(node.op)))
        if op is None:
            symbol = {ast.Pow: "**", ast.LShift: "<<", ast.RShift: ">>"}.get(
                type(node.op), type(node.op).__name__
            )
            raise ExprError(f"operator {symbol} is not allowed")
        left, right = self.build(node.left), self.build(node.right)
        return lambda ctx: checked(op(as_number(left(ctx)), as_number(right(ctx))))

    def on_Compare(self, node: ast.Compare) -> Thunk:
        ops = []
        for op in node.ops:
            fn = _CMPOPS.get(type(op))
            if fn is None:
                raise ExprError(f"comparison {type(op).__name__} is not allowed")
            ops.append(fn)
        operands = [self.build(node.left), *(self.build(c) for c in node.comparators)]

        def compare(ctx: EvalContext) -> bool:
            values = [o(ctx) for o in operands]
            return all(fn(values[i], values[i + 1]) for i, fn in enumerate(ops))

        return compare

    def on_IfExp(self, node: ast.IfExp) -> Thunk:
        test, body, orelse = self.build(node.test), self.build(node.body), self.build(node.orelse)
        return lambda ctx: body(ctx) if test(ctx) else orelse(ctx)

    def on_Call(self, node: ast.Call) -> Thunk:
        if not isinstance(node.func, ast.Name) or node.func.id not in _FUNCS:
            allowed = ", ".join(sorted(_FUNCS))
            raise ExprError(f"only these functions may be called: {allowed}")
        name = node.func.id
        if node.keywords or len(node.args) != _FUNCS[name]:
            raise ExprError(f"{name}() takes {_FUNCS[name]} positional argument(s)")
        if name in ("rising", "falling"):
            return self._edge(node, name == "rising")
        args = [self.build(a) for a in node.args]
        if name in CONVERSIONS:
            conv, arg = CONVERSIONS[name], args[0]
            return lambda ctx: conv(arg(ctx))
        if name == "abs":
            return lambda ctx: checked(abs(as_number(args[0](ctx))))
        pick = min if name == "min" else max
        return lambda ctx: pick(as_number(args[0](ctx)), as_number(args[1](ctx)))

    def _edge(self, node: ast.Call, rising: bool) -> Thunk:
        arg = node.args[0]
        if not isinstance(arg, ast.Name) or self.scope.names.get(arg.id) is not NameKind.BOOL:
            raise ExprError("rising()/falling() take the name of a bool symbol")
        name = arg.id
        self.reads.add(name)
        self.edges.add(name)
        if rising:
            return lambda ctx: bool(ctx.symbol(name)) and not ctx.previous(name)
        return lambda ctx: not ctx.symbol(name) and bool(ctx.previous(name))


def _iec_mod(a: Any, b: Any) -> int | float:
    """IEC's MOD: the remainder takes the dividend's sign (-7 MOD 3 is -1; `%` gives 2)."""
    if b == 0:
        raise ZeroDivisionError("MOD by zero")
    if isinstance(a, int) and isinstance(b, int):
        return abs(a) % abs(b) * (-1 if a < 0 else 1)
    return math.fmod(a, b)


def _describe(node: ast.AST) -> str:
    names = {
        "Lambda": "lambda",
        "ListComp": "a comprehension",
        "SetComp": "a comprehension",
        "DictComp": "a comprehension",
        "GeneratorExp": "a generator",
        "Subscript": "subscript []",
        "Starred": "*unpacking",
        "NamedExpr": "assignment :=",
        "JoinedStr": "an f-string",
        "Await": "await",
        "Yield": "yield",
        "List": "a list",
        "Tuple": "a tuple",
        "Dict": "a dict",
        "Set": "a set",
    }
    return names.get(type(node).__name__, type(node).__name__)


def parse(text: str) -> ast.expr:
    """Parse one expression; statements, imports and oversize input are rejected here."""
    return _parse(text)[0]


def _parse(text: str) -> tuple[ast.expr, frozenset[str]]:
    """The tree and the IEC words (AND, OR, NOT, MOD) the text used (core/iecwords.py)."""
    if len(text) > MAX_TEXT:
        raise ExprError(f"expression longer than {MAX_TEXT} characters")
    python, words = rewrite(text.strip())
    if "XOR" in words:
        raise ExprError(XOR_HINT)
    try:
        tree = ast.parse(python, mode="eval")
    except SyntaxError as exc:
        raise ExprError(f"syntax error: {exc.msg}") from None
    count = sum(1 for _ in ast.walk(tree))
    if count > MAX_NODES:
        raise ExprError(f"expression too complex ({count} nodes, at most {MAX_NODES})")
    return tree.body, words


def compile_expr(text: str | int | bool, scope: Scope) -> Compiled:
    """Compile `text` in `scope`. Raises ExprError; never runs any part of the text."""
    source = str(text).lower() if isinstance(text, bool) else str(text)
    tree, words = _parse(source)
    compiler = _Compiler(source, scope, words)
    fn = compiler.build(tree)
    return Compiled(source, fn, frozenset(compiler.reads), frozenset(compiler.edges),
                    frozenset(compiler.tokens), kind=static_kind(tree, _kinds(scope)), scope=scope)


def name_kind(t: SymType) -> NameKind:
    """How an expression reads a symbol of type `t`."""
    if t is SymType.BOOL:
        return NameKind.BOOL
    return NameKind.REAL if t in (SymType.REAL, SymType.LREAL) else NameKind.WORD


_KIND_OF = {NameKind.BOOL: "bool", NameKind.WORD: "int", NameKind.REAL: "float",
            NameKind.EVENT: "bool"}


def _kinds(scope: Scope) -> Callable[[str], str]:
    def kind(name: str) -> str:
        if name in scope.consts:
            const = scope.consts[name]
            return {bool: "bool", int: "int", float: "float", str: "text"}.get(type(const), "any")
        found = scope.names.get(name)
        if found is None:
            return "bool" if name in _CONSTS else "any"
        return _KIND_OF.get(found, "any")
    return kind


def names_in(text: str) -> set[str]:
    """Bare names an expression mentions (for subnet parameter checks); [] on a parse error."""
    try:
        tree = parse(text)
    except ExprError:
        return set()
    return {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}


def substitute(text: str, mapping: Mapping[str, Value]) -> str:
    """Replace bare names (subnet parameters) at the ast level: a text value renames the name
    (a symbol of the instance), a number or bool becomes a literal."""
    tree, words = _parse(text)

    class Rename(ast.NodeTransformer):
        def visit_Name(self, node: ast.Name) -> ast.AST:
            if node.id not in mapping:
                return node
            value = mapping[node.id]
            new: ast.AST = (
                ast.Name(id=value, ctx=node.ctx) if isinstance(value, str) else ast.Constant(value)
            )
            return ast.copy_location(new, node)

    text = ast.unparse(Rename().visit(tree))
    return unrewrite(text) if words else text
