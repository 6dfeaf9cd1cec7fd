"""The net as the operator's page draws it: structure once per program, live state per board.

Owns: the "net" part of the status board (places, transitions, arcs, the subnet instance of
each node, place-attached and busy outputs, guards and timing as text) and its "net_live"
part (timed firings in progress with their remaining time, coloured tokens, how often each
transition fired). Both are capped so that a very large net never fills the board.
Does not know: HTTP, the browser, how the board is shared, clocks (`now_ns` is an argument).
"""

from __future__ import annotations

from typing import Any, Final

from softplc.core.net import CompiledNet, NetState
from softplc.core.present import entry_form

MAX_NODES: Final = 1500  # beyond this the page shows counts only (the board is 1 MiB)
MAX_TOKENS_SHOWN: Final = 8  # coloured tokens per place on the board
_cache: dict[int, tuple[CompiledNet, dict[str, Any]]] = {}


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
    """The drawable structure of `net` (computed once per compiled net). Never raises: a
    bug here must not stop the scan that publishes it."""
    try:
        return _structure(net)
    except Exception as exc:
        return {"error": f"net structure unavailable ({type(exc).__name__}: {exc})"}


def forget() -> None:
    """Drop the cached structure (its net was replaced: the loop lets go of that net off the
    scan thread, and this cache must not be what frees it later)."""
    _cache.clear()


def _structure(net: CompiledNet) -> dict[str, Any]:
    cached = _cache.get(id(net))
    if cached is not None and cached[0] is net:
        return cached[1]
    places, transitions = net.place_names, net.transitions
    document: dict[str, Any] = {"program": net.name, "program_hash": net.program_hash,
                                "places": len(places), "transitions": len(transitions),
                                "subnets": list(net.subnets), "symbols": _symbols(net)}
    if len(places) + len(transitions) <= MAX_NODES:
        document["nodes"] = _nodes(net)
        document["arcs"] = _arcs(net)
    else:
        document["too_large"] = True
    _cache.clear()  # one program at a time: keep only the newest
    _cache[id(net)] = (net, document)
    return document


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
