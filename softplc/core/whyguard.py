"""Why a guard is false: the part of it that is, with the values of the names it read.

Owns: evaluating a transition's guard off the round (core/why.py asks), splitting a guard
`a and b and c` into the parts that are false, and the values each part read (symbols with
their previous value where it takes an edge, events, token fields, forced symbols marked),
each symbol's value as core/present.py writes it (a real as a real, a scaled one with its unit).
Does not know: the firing round (core/why.py runs it), where the values come from.
"""

from __future__ import annotations

import ast
import functools
import itertools
import math
from collections.abc import Mapping

from softplc.core.engine.bindings import Bound
from softplc.core.expr import Compiled, EvalContext, ExprError, NameKind, compile_expr, parse
from softplc.core.iecwords import unrewrite
from softplc.core.net import CompiledNet, NetState, Token, Transition
from softplc.core.nonfinite import door
from softplc.core.present import text as value_text

MAX_TRIES = 200  # token combinations tried for a coloured guard (the round's own bound: 1000)


def guard_reasons(net: CompiledNet, state: NetState, ctx: EvalContext, t: Transition,
                  forced: Mapping[str, object]) -> list[tuple[str, tuple[str, ...]]]:
    """[] when the guard holds (for some binding); else per false part its text and the
    symbols it read."""
    guard = t.guard
    if guard is None:
        return []
    envs = _bindings(state, t) if t.coloured else [{}]
    for env in envs:
        try:
            if _eval(guard, ctx, env):
                return []
        except Exception as exc:  # the round counts a raising guard as false (a diagnostic)
            return [(f"guard {guard.text} raised {type(exc).__name__}: {exc} (false for this "
                     "round)", tuple(sorted(guard.reads)))]
    env = envs[0] if envs else {}
    parts = _false_parts(guard, ctx, env)
    every = f" for each of {len(envs)} binding(s) tried" if t.coloured else ""
    out = []
    for text, part in parts:
        which = f"guard {guard.text}{every}: {text} is false" if text != guard.text \
            else f"guard {guard.text} is false{every}"
        out.append((f"{which} with {_values(net, part, ctx, env, forced)}",
                    tuple(sorted(part.reads))))
    return out


def _eval(guard: Compiled, ctx: EvalContext, env: Mapping[str, Token]) -> bool:
    return bool(guard(Bound(ctx, env) if env else ctx))


def _bindings(state: NetState, t: Transition) -> list[dict[str, Token]]:
    """Token variable -> token, for the first MAX_TRIES combinations of distinct tokens."""
    arcs = [a for a in t.pre if a.var is not None]
    pools = [list(enumerate(state.tokens.get(a.place, []))) for a in arcs]
    out: list[dict[str, Token]] = []
    for combo in itertools.islice(itertools.product(*pools), MAX_TRIES):
        seen = [(a.place, i) for a, (i, _) in zip(arcs, combo, strict=True)]
        if len(set(seen)) == len(seen):
            out.append({str(a.var): tok for a, (_, tok) in zip(arcs, combo, strict=True)})
    return out


def _false_parts(guard: Compiled, ctx: EvalContext,
                 env: Mapping[str, Token]) -> list[tuple[str, Compiled]]:
    """The conjuncts of `a and b and c` that are false; the whole guard otherwise."""
    whole = [(guard.text, guard)]
    parts = _conjuncts(guard)
    if parts is None:
        return whole
    false = []
    for text, part in parts:
        try:
            if not _eval(part, ctx, env):
                false.append((text, part))
        except Exception:  # a part that raises: the whole guard is shown instead
            continue
    return false or whole


# guard -> its conjuncts, compiled once: the status document asks every ~50 ms for what blocks
# the waiting transitions (core/waiting.py), and a parse there cost a compile per part each
# time (and, on CPython 3.11, raced other threads' parses: gh-106905). Keyed by id, the guard kept.
_CONJUNCTS: dict[int, tuple[Compiled, tuple[tuple[str, Compiled], ...] | None]] = {}
MAX_CACHED = 4096


def _conjuncts(guard: Compiled) -> tuple[tuple[str, Compiled], ...] | None:
    """The parts of a guard `a and b and c`, each compiled (None: not a conjunction)."""
    hit = _CONJUNCTS.get(id(guard))
    if hit is not None and hit[0] is guard:
        return hit[1]
    parts: tuple[tuple[str, Compiled], ...] | None = None
    try:
        tree = parse(guard.text) if guard.scope is not None else None
    except ExprError:
        tree = None
    if isinstance(tree, ast.BoolOp) and isinstance(tree.op, ast.And) and guard.scope is not None:
        found = []
        for node in tree.values:
            text = unrewrite(ast.unparse(node))  # NOT and MOD as written (core/iecwords.py)
            try:
                found.append((text, compile_expr(text, guard.scope)))
            except Exception:  # a part that does not compile alone: left out, as before
                continue
        parts = tuple(found)
    if len(_CONJUNCTS) >= MAX_CACHED:
        _CONJUNCTS.clear()
    _CONJUNCTS[id(guard)] = (guard, parts)
    return parts


def _values(net: CompiledNet, expr: Compiled, ctx: EvalContext, env: Mapping[str, Token],
            forced: Mapping[str, object]) -> str:
    """`s2_i = 1 (forced), d.count = 2, event e did not occur`: what `expr` read."""
    kinds = expr.scope.names if expr.scope is not None else {}
    shown = []
    for name in sorted(expr.reads):
        if kinds.get(name) is NameKind.EVENT or name not in net.io.symbols:
            shown.append(f"event {name} {'occurred' if ctx.event(name) else 'did not occur'}")
            continue
        sym = net.io.symbols[name]
        kind = sym.type.value
        value = ctx.symbol(name)
        text = f"{name} = {value_text(kind, value, sym.scaling)}"
        if isinstance(value, float) and not math.isfinite(value):  # core/nonfinite.py
            text += f" (not a number: it came in through {door(sym)})"
        if name in expr.edges:
            text += f" (previous scan {value_text(kind, ctx.previous(name), sym.scaling)})"
        if name in forced:
            text += " (forced)"
        shown.append(text)
    for var, field in _fields(expr.text):
        record = env.get(var)
        if record is not None:
            shown.append(f"{var}.{field} = {record.get(field, '(no such field)')}")
    return ", ".join(shown) or "no names read"


@functools.lru_cache(maxsize=4096)
def _fields(text: str) -> tuple[tuple[str, str], ...]:
    """The `var.field` reads of an expression, in order, once each."""
    try:
        tree = parse(text)
    except ExprError:
        return ()
    found = [(n.value.id, n.attr) for n in ast.walk(tree)
             if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Name)]
    return tuple(dict.fromkeys(found))
