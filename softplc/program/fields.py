"""Token fields a place's tokens can have, and expressions that read fields they cannot.

Owns: inferring the record fields of each coloured place (from its initial tokens and from
every production into it, passed-through tokens carrying their place's fields, to a fixed
point) and the located problem for `x.field` where no token of x's place has `field`, with a
"did you mean". Does not know: evaluating expressions (the text is only parsed, never run).
"""

from __future__ import annotations

import ast
from collections.abc import Callable, Iterator, Sequence

from softplc.core.expr import MAX_TEXT, ExprError, parse
from softplc.core.net import Transition
from softplc.program.specvalues import ProgramSpec, TransitionSpec, Where
from softplc.program.suggest import did_you_mean


def place_fields(spec: ProgramSpec, transitions: Sequence[Transition]) -> list[set[str] | None]:
    """Per place: the fields its tokens can have (None: not coloured)."""
    fields: list[set[str] | None] = [
        {k for r in (p.records or ()) for k in r} if p.coloured else None for p in spec.places]
    changed = True
    while changed:  # a fixed point: pass-through tokens carry their input place's fields
        changed = False
        for t in transitions:
            bound = {a.var: a.place for a in t.pre if a.var is not None}
            for o in t.post:
                target = fields[o.place]
                if target is None:
                    continue
                new = set(o.fields or ()) if o.fields is not None else set()
                if o.var is not None and o.var in bound:
                    new |= fields[bound[o.var]] or set()
                if not new <= target:
                    target |= new
                    changed = True
    return fields


def check(spec: ProgramSpec, transitions: Sequence[Transition],
          problem: Callable[[Where, str], None]) -> None:
    """A problem for every `var.field` read that no token of var's place can have."""
    fields = place_fields(spec, transitions)
    for t, ts in zip(transitions, spec.transitions, strict=True):
        bound = {a.var: a.place for a in t.pre if a.var is not None}
        for text, where in _expressions(ts):
            for var, name in _reads(text):
                place = bound.get(var)
                known = fields[place] if place is not None else None
                if not known or name in known:  # no records at all: nothing to go by
                    continue
                problem(where, f"token field {var}.{name}: no token of place "
                        f"{spec.places[place].name!r} has it (its tokens have "  # type: ignore[index]
                        f"{', '.join(sorted(known))}){did_you_mean(name, known)}")


def _expressions(ts: TransitionSpec) -> Iterator[tuple[str, Where]]:
    if ts.when is not None:
        yield ts.when
    yield from ts.actions
    for arc in ts.post:
        if isinstance(arc.token, dict):
            for value in arc.token.values():
                if isinstance(value, str):
                    yield value, arc.where


def _reads(text: str) -> Iterator[tuple[str, str]]:
    """(var, field) of every `var.field` in `text` (an assignment's right side too)."""
    if len(text) > MAX_TEXT:
        return  # the expression compiler reports it (10,000 x `not ` was a MemoryError here)
    try:
        tree = parse(text.partition("=")[2] if _assignment(text) else text)  # IEC words too
    except (ExprError, MemoryError, RecursionError):
        return  # the expression compiler reports it
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            yield node.value.id, node.attr


def _assignment(text: str) -> bool:
    head, sep, _ = text.partition("=")
    return bool(sep) and head.strip().isidentifier() and not text.partition("=")[2].startswith("=")
