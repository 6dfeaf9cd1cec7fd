"""What the debug adapter shows in its scopes, as trees of named values built from the API's
answers (debug/dap.py turns them into DAP variables with references).

Owns: the Marking scope (every place's token count, a coloured place's records under it), the
Symbols scope (typed values as status shows them, unit and force noted), the Why scope (the
verdict, the reasons, the feeders one level down each).
Does not know: DAP's references, HTTP, how the PLC computes any of it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True, slots=True)
class Var:
    name: str
    value: str
    type: str = ""
    children: tuple[Var, ...] = ()


def marking_vars(status: Mapping[str, Any], places: Iterable[str] = ()) -> list[Var]:
    """Every place of `places` and of the status's marking (an empty place: 0)."""
    marking: Mapping[str, int] = status.get("marking") or {}
    tokens: Mapping[str, list[Any]] = status.get("tokens") or {}
    names = sorted(set(places) | set(marking))
    return [Var(name, str(marking.get(name, 0)), "tokens",
                tuple(_tree(f"[{i}]", record) for i, record in enumerate(tokens.get(name, ()))))
            for name in names]


def symbol_vars(symbols: Mapping[str, Mapping[str, Any]],
                forced: Mapping[str, Any]) -> list[Var]:
    vars_ = []
    for name in sorted(symbols):
        entry = symbols[name]
        text = value_text(entry.get("value"))
        if entry.get("unit"):
            text += f" {entry['unit']}"
        if name in forced:
            text += " (forced)"
        kind = " ".join(str(entry[k]) for k in ("type", "direction", "address") if entry.get(k))
        vars_.append(Var(name, text, kind))
    return vars_


def why_vars(answer: Mapping[str, Any]) -> list[Var]:
    """The verdict first, then one variable per reason (its kind: its text), then the
    transitions that feed a missing place."""
    head = [Var("verdict", str(answer.get("verdict")), "verdict")]
    if answer.get("scan") is not None:
        head.append(Var("scan", str(answer["scan"]), "scan"))
    reasons = [Var(f"{i + 1}. {r.get('kind', 'reason')}", str(r.get("text", "")), "reason")
               for i, r in enumerate(answer.get("reasons") or [])]
    feeders = [Var(f"fed by {f.get('transition')}", str(f.get("verdict")), "verdict",
                   tuple(why_vars(f)[1:]))
               for f in answer.get("feeders") or []]
    notes = [Var("basis", str(answer["basis"]))] if answer.get("basis") else []
    return head + reasons + feeders + notes


def _tree(name: str, value: Any) -> Var:
    if isinstance(value, Mapping):
        return Var(name, value_text(value), "record",
                   tuple(_tree(str(k), v) for k, v in value.items()))
    return Var(name, value_text(value))


def value_text(value: Any) -> str:
    if isinstance(value, str):
        return value  # "NaN", "Infinity": a real that holds one
    return json.dumps(value, sort_keys=True)
