"""What the debug adapter shows in its scopes, as trees of named values built from the API's
answers (debug/dap.py turns them into DAP variables with references).

Owns: the Marking scope (every place's token count, a coloured place's records under it), the
Symbols scope (typed values as live `why` shows them, core/present.py: a real as a real, a
scaled symbol in engineering units with its unit, force noted, the stored bits in a child
`raw`), the Why scope (the verdict, the reasons, the feeders one level down each).
Does not know: DAP's references, HTTP, how the PLC computes any of it.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from softplc.core import present
from softplc.core.datatypes import INFO, SymType, value_of


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
    return [symbol_var(name, symbols[name], name in forced) for name in sorted(symbols)]


def symbol_var(name: str, entry: Mapping[str, Any], forced: bool = False) -> Var:
    """A symbol as live `why` and the VCD show it (core/present.py): a real as a real, a
    scaled symbol in engineering units at its scale's resolution with its unit; the stored
    bits the API reads at its location (a real's pattern, a scaled symbol's raw count, not
    converted back from the value: a clamped scale's out-of-range count shows) in `raw`."""
    kind, scale = entry.get("type"), entry.get("scale")
    value = entry.get("value")
    text = present.text(kind, value, scale) if isinstance(value, bool | int | float) \
        else value if isinstance(value, str) else value_text(value)  # "NaN": a real's
    if forced:
        text += " (forced)"
    where = " ".join(str(entry[k]) for k in ("type", "direction", "address") if entry.get(k))
    if entry.get("unit"):
        where += f" scaled, {entry['unit']}"
    raw = _raw(entry)
    return Var(name, text, where, (raw,) if raw is not None else ())


def _raw(entry: Mapping[str, Any]) -> Var | None:
    """What the symbol's location holds (the API's `raw`), unconverted; none for a bit."""
    bits, t = entry.get("raw"), present.sym_type(entry.get("type"))
    if type(bits) is not int or t is None or t is SymType.BOOL:
        return None
    count = bits if INFO[t].is_float else value_of(t, bits)  # an integer's count, signed
    return Var("raw", f"{count} (0x{bits:0{INFO[t].bits // 4}X})",
               f"{'raw count' if 'scale' in entry else 'stored bits'} of {entry.get('address')}")


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
