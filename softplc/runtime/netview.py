"""The net as the operator's page draws it: what a program is, once per program; live state
per board.

Owns: the "net" part of the status board (places, transitions, arcs, the subnet instance of
each node, place-attached and busy outputs, guards and timing as text), the fixed part of
each "symbols" entry (all but its value), and its "net_live" part (timed firings in progress
with their remaining time, coloured tokens, how often each transition fired). Both are capped
so that a very large net never fills the board. What is fixed per program is described once,
before a download's swap scan (`prewarm`, between scans while it is prepared), so that the
swap scan publishes the new program's board without describing it.
Does not know: HTTP, the browser, how the board is shared, clocks (`now_ns` is an argument).
"""

from __future__ import annotations

from typing import Any, Final, NamedTuple

from softplc.core.net import CompiledNet, NetState
from softplc.core.present import entry_form
from softplc.core.symbols import IoImage, Symbol

MAX_NODES: Final = 1500  # beyond this the page shows counts only (the board is 1 MiB)
MAX_TOKENS_SHOWN: Final = 8  # coloured tokens per place on the board
KEPT: Final = 2  # programs described: the running one and the one being downloaded


class Described(NamedTuple):
    """What the board shows of a program that does not change while it runs."""

    structure: dict[str, Any]
    # (symbol, its board entry without the value: statusdoc sets "value" and "raw")
    symbols: tuple[tuple[Symbol, dict[str, Any]], ...]


# By program hash and io image (the hash leaves out texts that do not change the PLC's
# behaviour, descriptions and units, which the board shows), newest last; the
# io image is kept with its entry, so that its identity stays its own. No net is kept here:
# letting go of a net is the loop's, off the scan thread.
_cache: dict[tuple[str, int], tuple[IoImage, Described]] = {}


def _instance(name: str, subnets: tuple[str, ...]) -> str | None:
    """The subnet instance a node belongs to: the longest instance prefix of its name."""
    best = None
    for inst in subnets:
        if name.startswith(inst + ".") and (best is None or len(inst) > len(best)):
            best = inst
    return best


def _ms(ns: int) -> float:
    return round(ns / 1e6, 3)


def structure(net: CompiledNet) -> dict[str, Any]:
    """The drawable structure of `net` (described once per program). Never raises: a bug here
    must not stop the scan that publishes it."""
    return described(net).structure


def prewarm(net: CompiledNet) -> None:
    """Describe `net` now, before its swap scan publishes its board (runtime/prepare.py)."""
    described(net)


def described(net: CompiledNet) -> Described:
    """`net` described: from the cache when it was described before (by its io image: one
    per compile, the same object from a download's preparation to its swap)."""
    key = (net.program_hash, id(net.io))
    hit = _cache.pop(key, None)
    if hit is None:
        hit = (net.io, Described(_structure(net),
                                 tuple((s, _fixed(s)) for s in net.io.symbols.values())))
        while len(_cache) >= KEPT:
            del _cache[next(iter(_cache))]
    _cache[key] = hit  # the newest last
    return hit[1]


def _structure(net: CompiledNet) -> dict[str, Any]:
    try:
        return _drawn(net)
    except Exception as exc:
        return {"error": f"net structure unavailable ({type(exc).__name__}: {exc})"}


def _drawn(net: CompiledNet) -> dict[str, Any]:
    places, transitions = net.place_names, net.transitions
    document: dict[str, Any] = {"program": net.name, "program_hash": net.program_hash,
                                "places": len(places), "transitions": len(transitions),
                                "subnets": list(net.subnets), "symbols": _symbols(net)}
    if len(places) + len(transitions) <= MAX_NODES:
        document["nodes"] = _nodes(net)
        document["arcs"] = _arcs(net)
    else:
        document["too_large"] = True
    return document


def _fixed(s: Symbol) -> dict[str, Any]:
    """A symbol's board entry without its value, in the entry's order (statusdoc sets `value`
    as people read it and `raw`, the bits its location holds)."""
    entry: dict[str, Any] = {
        "address": str(s.address), "type": s.type.value, "direction": s.direction.value,
        "value": None, "raw": 0, "hmi_writable": s.hmi_writable,
        "description": s.description}
    if s.scaling is not None:  # the value is in engineering units; the raw count in `raw`
        entry["scale"] = s.scaling.as_dict()
        entry["unit"] = s.scaling.unit
    if not s.finite:  # the Modbus slave lets a NaN's bits in (core/nonfinite.py)
        entry["finite"] = False
    return entry


def _nodes(net: CompiledNet) -> dict[str, list[dict[str, Any]]]:
    subnets = net.subnets
    places = [{
        "name": name, "instance": _instance(name, subnets), "initial": int(net.initial[p]),
        "capacity": int(net.capacity[p]), "coloured": bool(net.coloured[p]),
        "outputs": [[s, v] for s, v in net.place_outputs.get(p, ())],
    } for p, name in enumerate(net.place_names)]
    rank = net.rank
    transitions = []
    for t in net.transitions:
        entry: dict[str, Any] = {
            "name": t.name, "instance": _instance(t.name, subnets), "priority": t.priority,
            "rank": rank[t.index], "guard": t.guard.text if t.guard is not None else None,
            "delay_ms": _ms(t.delay_ns), "duration_ms": _ms(t.duration_ns),
            "outputs": [[s, v] for s, v in t.busy_outputs],
            "actions": [a.kind.value + " " + a.target if a.value is None
                        else f"{a.target} = {a.value.text}" for a in t.actions],
        }
        transitions.append(entry)
    return {"places": places, "transitions": transitions}


def _symbols(net: CompiledNet) -> list[dict[str, Any]]:
    """The process image table's static columns, in address order."""
    ordered = sorted(net.io.symbols.values(), key=lambda s: (s.direction.value, s.address.attr,
                                                           s.address.index))
    return [{"name": s.name, "address": str(s.address), "type": s.type.value,
             "direction": s.direction.value, "description": s.description,
             "hmi_writable": s.hmi_writable and s.direction.value != "in", "safe": s.safe,
             **entry_form(s.type.value, s.scaling)}  # unit, input range, display precision
            for s in ordered]


def _arcs(net: CompiledNet) -> list[list[Any]]:
    """[source, target, weight, kind] with kind "normal", "test" or "inhibitor"."""
    names = net.place_names
    arcs: list[list[Any]] = []
    for t in net.transitions:
        arcs += [[names[a.place], t.name, a.weight, "normal"] for a in t.pre]
        arcs += [[t.name, names[a.place], a.weight, "normal"] for a in t.post]
        arcs += [[names[p], t.name, w, "test"] for p, w in t.test]
        arcs += [[names[p], t.name, w, "inhibitor"] for p, w in t.inhibit]
    return arcs


def live(net: CompiledNet | None, state: NetState | None, now_ns: int,
         fired_counts: dict[str, int]) -> dict[str, Any]:
    """Busy firings (remaining ms), coloured tokens and fire counts, for the board. Never
    raises, like structure()."""
    try:
        return _live(net, state, now_ns, fired_counts)
    except Exception as exc:
        return {"error": f"live net unavailable ({type(exc).__name__}: {exc})"}


def _live(net: CompiledNet | None, state: NetState | None, now_ns: int,
          fired_counts: dict[str, int]) -> dict[str, Any]:
    if net is None or state is None:
        return {}
    if len(net.place_names) + len(net.transitions) > MAX_NODES:
        return {"busy": len(state.busy)}
    busy = {net.transitions[t].name: {"remaining_ms": _ms(max(b.end_ns - now_ns, 0)),
                                      "duration_ms": _ms(net.transitions[t].duration_ns)}
            for t, b in state.busy.items()}
    waiting = {net.transitions[t].name: _ms(max(net.transitions[t].delay_ns
                                                - (now_ns - since), 0))
               for t, since in state.enabled_since.items() if net.transitions[t].delay_ns}
    tokens = {net.place_names[p]: [dict(tok) for tok in toks[:MAX_TOKENS_SHOWN]]
              for p, toks in state.tokens.items() if toks}
    return {"busy": busy, "delay_left_ms": waiting, "tokens": tokens,
            "fired_counts": dict(fired_counts)}
