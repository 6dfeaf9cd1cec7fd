"""Seeded AST mutants of one Python module (issue 43): source text in, mutated source text out.

Owns: the operators (comparison flips, arithmetic swaps, constants +/-1, and/or swaps, `not`
removed, `return None`, an early return, a statement deleted), where they apply (never inside
an annotation, a docstring or a logging call), each mutant's key, and the seeded sample.
Does not know: files, pytest, which tests belong to which module (mutate.py runs them).
"""

from __future__ import annotations

import ast
import random
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

COMPARE_FLIP: dict[type[ast.cmpop], type[ast.cmpop]] = {
    ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq, ast.NotEq: ast.Eq, ast.Is: ast.IsNot, ast.IsNot: ast.Is,
    ast.In: ast.NotIn, ast.NotIn: ast.In,
}
ARITH_SWAP: dict[type[ast.operator], type[ast.operator]] = {
    ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult,
    ast.FloorDiv: ast.Mult, ast.Mod: ast.FloorDiv, ast.Pow: ast.Mult,
    ast.LShift: ast.RShift, ast.RShift: ast.LShift, ast.BitAnd: ast.BitOr,
    ast.BitOr: ast.BitAnd, ast.BitXor: ast.BitAnd,
}
# Deleting one of these changes what the module does; deleting a def, an import or a `pass`
# only makes a NameError or nothing at all.
# (A deleted `return x` is `return None`'s twin: not deleted.)
DELETABLE = (ast.Expr, ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Raise, ast.Assert,
             ast.If, ast.For, ast.While, ast.With, ast.Try, ast.Delete)
# Deleting a log line is equivalent for every test but a log test: not worth a mutant each.
LOGGERS = frozenset({"log", "logger", "logging", "_log"})
SNIPPET = 70


@dataclass(frozen=True, slots=True)
class Site:
    """One mutation of a module: where, what, and how to apply it to the tree it was found in."""

    line: int
    scope: str  # the enclosing class and function names, "Class.method", or "<module>"
    operator: str
    before: str
    after: str
    apply: Callable[[], None]

    @property
    def description(self) -> str:
        return f"{self.operator}: `{self.before}` -> `{self.after}`"


def _text(node: ast.AST) -> str:
    return " ".join(ast.unparse(node).split())


def _trimmed(before: str, after: str) -> tuple[str, str]:
    """Both texts cut to SNIPPET characters around the first one that differs."""
    at = next((i for i, (a, b) in enumerate(zip(before, after, strict=False)) if a != b),
              min(len(before), len(after)))
    start = max(0, at - SNIPPET // 3) if max(len(before), len(after)) > SNIPPET else 0

    def cut(text: str) -> str:
        return ("..." if start else "") + text[start:start + SNIPPET] + (
            "..." if start + SNIPPET < len(text) else "")
    return cut(before), cut(after)


def _is_docstring(stmt: ast.stmt) -> bool:
    return isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Constant) and \
        isinstance(stmt.value.value, str)


def _is_log_call(stmt: ast.stmt) -> bool:
    if not (isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Call)):
        return False
    func = stmt.value.func
    return isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) and \
        func.value.id in LOGGERS


def _setter(node: ast.AST, field: str, value: object) -> Callable[[], None]:
    def apply() -> None:
        setattr(node, field, value)
    return apply


def _list_setter(items: list[Any], index: int, value: ast.AST) -> Callable[[], None]:
    def apply() -> None:
        items[index] = value
    return apply


def _insert(body: list[ast.stmt], index: int, value: ast.stmt) -> Callable[[], None]:
    def apply() -> None:
        body.insert(index, value)
    return apply


class _Finder:
    """Walks a module in source order and collects its sites (the same order every time)."""

    def __init__(self) -> None:
        self.sites: list[Site] = []
        self._scope: list[str] = []
        self._in_function = 0

    def _add(self, node: ast.AST, operator: str, after: ast.AST | str,
             apply: Callable[[], None], before: str | None = None) -> None:
        line = getattr(node, "lineno", 0)
        old, new = _trimmed(_text(node) if before is None else before,
                            after if isinstance(after, str) else _text(after))
        self.sites.append(Site(line, ".".join(self._scope) or "<module>", operator, old, new,
                               apply))

    def visit(self, node: ast.AST) -> None:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            self._scope.append(node.name)
            is_function = not isinstance(node, ast.ClassDef)
            self._in_function += is_function
            if not isinstance(node, ast.ClassDef):
                self._early_return(node)
                self.visit(node.args)
            self._statements(node.body)
            for stmt in node.body:
                self.visit(stmt)
            self._in_function -= is_function
            self._scope.pop()
            return
        self._sites_of(node)
        for field, value in ast.iter_fields(node):
            if field in ("annotation", "returns", "type_comment"):
                continue  # never run: `from __future__ import annotations`
            if isinstance(value, list):
                self._statements(value)
                for index, item in enumerate(value):
                    if isinstance(item, ast.AST):
                        self._not_removed(item, partial(_list_setter, value, index))
                        self.visit(item)
            elif isinstance(value, ast.AST):
                self._not_removed(value, partial(_setter, node, field))
                self.visit(value)

    def _not_removed(self, node: ast.AST, put: Callable[[ast.AST], Callable[[], None]]) -> None:
        """`not x` -> `x`: the operand takes the UnaryOp's place in its parent."""
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not):
            self._add(node, "not removed", node.operand, put(node.operand))

    def _statements(self, body: list[Any]) -> None:
        if not self._in_function:
            return
        for index, stmt in enumerate(body):
            if not isinstance(stmt, DELETABLE) or _is_docstring(stmt) or _is_log_call(stmt):
                continue
            self._add(stmt, "delete statement", "pass",
                      _list_setter(body, index, ast.Pass()), _first_line(stmt))

    def _early_return(self, func: ast.FunctionDef | ast.AsyncFunctionDef) -> None:
        at = 1 if func.body and _is_docstring(func.body[0]) else 0
        if at < len(func.body) and isinstance(func.body[at], ast.Return):
            return  # the first statement returns already: `return None` instead covers it
        self._add(func, "early return", "return None",
                  _insert(func.body, at, ast.Return(ast.Constant(None))), f"def {func.name}")

    def _sites_of(self, node: ast.AST) -> None:
        if isinstance(node, ast.Compare):
            for index, op in enumerate(node.ops):
                flipped = COMPARE_FLIP.get(type(op))
                if flipped is not None:
                    ops = list(node.ops)
                    ops[index] = flipped()
                    self._add(node, "compare", ast.Compare(node.left, ops, node.comparators),
                              _setter(node, "ops", ops))
        elif isinstance(node, ast.BinOp | ast.AugAssign):
            swapped = ARITH_SWAP.get(type(node.op))
            if swapped is not None:
                shown = ast.BinOp(node.left, swapped(), node.right) \
                    if isinstance(node, ast.BinOp) else \
                    ast.AugAssign(node.target, swapped(), node.value)
                self._add(node, "arithmetic", shown, _setter(node, "op", swapped()))
        elif isinstance(node, ast.BoolOp):
            other = ast.Or() if isinstance(node.op, ast.And) else ast.And()
            self._add(node, "and/or", ast.BoolOp(other, node.values), _setter(node, "op", other))
        elif isinstance(node, ast.Constant) and isinstance(node.value, int | float) \
                and not isinstance(node.value, bool):
            for delta in (1, -1):
                value = node.value + delta
                self._add(node, f"constant {delta:+d}", repr(value),
                          _setter(node, "value", value))
        elif isinstance(node, ast.Return) and node.value is not None and not (
                isinstance(node.value, ast.Constant) and node.value.value is None):
            self._add(node, "return None", "return None",
                      _setter(node, "value", ast.Constant(None)))


def _first_line(stmt: ast.stmt) -> str:
    text = ast.unparse(stmt).splitlines()[0]
    return text + " ..." if isinstance(stmt, ast.If | ast.For | ast.While | ast.With
                                       | ast.Try) else text


def sites(tree: ast.Module) -> list[Site]:
    """Every mutation of `tree`, in source order; each Site's apply() changes this tree."""
    finder = _Finder()
    for stmt in tree.body:
        finder.visit(stmt)
    return finder.sites


@dataclass(frozen=True, slots=True)
class Mutant:
    path: str  # relative to the tree's root
    index: int  # which site of the module, in source order
    line: int
    description: str
    key: str  # names the mutant across runs and line shifts (the equivalents file's key)


def every(path: str, source: str) -> list[Mutant]:
    """All the module's mutants, in source order."""
    seen: dict[str, int] = {}
    found = []
    for index, site in enumerate(sites(ast.parse(source, path))):
        key = f"{path}::{site.scope}::{site.description}"
        seen[key] = seen.get(key, 0) + 1
        found.append(Mutant(path, index, site.line, site.description,
                            key if seen[key] == 1 else f"{key} #{seen[key]}"))
    return found


def sample(path: str, source: str, size: int, seed: int) -> tuple[list[Mutant], int]:
    """`size` of the module's mutants drawn by `seed` (all when it has fewer), in the order
    of the draw (not source order: a run the budget cuts after its first k mutants has run a
    fair sample of k, not the top of the module); with the number of sites they were drawn
    from."""
    found = every(path, source)
    picked = random.Random(f"{seed}:{path}").sample(range(len(found)), min(size, len(found)))
    return [found[i] for i in picked], len(found)


def mutated(source: str, mutant: Mutant) -> str:
    """The module's text with `mutant` applied (formatting and comments are not kept)."""
    tree = ast.parse(source, mutant.path)
    site = sites(tree)[mutant.index]
    site.apply()
    return ast.unparse(ast.fix_missing_locations(tree)) + "\n"


def unmutated(source: str, path: str) -> str:
    """The module as mutated() writes it, with no mutation: the baseline the tests must pass."""
    return ast.unparse(ast.parse(source, path)) + "\n"
