"""What an exploration found, before it is turned into findings and JSON.

Owns: Graph (counts, bounds, deadlocks with their paths, fired transitions, conflicts,
unbounded places with their covering witness) and the output-conflict rules shared by both
explorers. Does not know: how states are enumerated, files, the CLI.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from softplc.analysis.model import AnalysisNet, WriteValue


@dataclass(frozen=True, slots=True)
class Conflict:
    symbol: str
    drivers: tuple[str, ...]  # e.g. "place p = 1", "transition t: reset"
    locations: tuple[str, ...]  # FILE:LINE of each driver
    path: tuple[str, ...]  # steps from the initial state to the state or step


@dataclass(frozen=True, slots=True)
class Deadlock:
    marking: dict[str, int]
    path: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class Unbounded:
    place: int
    witness: str  # the covering pair, in words


@dataclass(slots=True)
class Graph:
    semantics: str
    states: int = 0
    edges: int = 0
    complete: bool = True
    bounds: list[int | None] = field(default_factory=list)  # None: unbounded (omega)
    max_marking: int | None = 0
    deadlocks: list[Deadlock] = field(default_factory=list)
    deadlock_count: int = 0
    fired: list[bool] = field(default_factory=list)
    conflicts: list[Conflict] = field(default_factory=list)
    unbounded: list[Unbounded] = field(default_factory=list)
    bytes_per_state: float = 0.0
    notes: list[str] = field(default_factory=list)
    stopped: str = ""  # why an incomplete exploration stopped, when not at max_states


MAX_REPORTED = 20  # deadlocks and conflicts listed in full (all are counted)


def state_conflicts(net: AnalysisNet, marked: Sequence[int], busy: Sequence[int]
                    ) -> list[tuple[str, list[tuple[str, str, int]]]]:
    """Symbols driven to different values by the marked places and busy transitions of one
    state: (symbol, [(kind and name, location, value)])."""
    drivers: dict[str, list[tuple[str, str, int]]] = {}
    for p in marked:
        for sym, value in net.moore.get(p, ()):
            drivers.setdefault(sym, []).append(
                (f"place {net.place_names[p]}", net.where_place(p), value))
    for t in busy:
        for sym, value in net.busy_outputs.get(t, ()):
            drivers.setdefault(sym, []).append(
                (f"transition {net.transition_names[t]} (running)", net.where_transition(t), value))
    return [(s, d) for s, d in sorted(drivers.items()) if len({v for _, _, v in d}) > 1]


def moore_value(net: AnalysisNet, sym: str, marked: Sequence[int], busy: Sequence[int]) -> int:
    """What the engine writes for a place-driven symbol: the first non-zero driver value."""
    value = 0
    for p in marked:
        for s, v in net.moore.get(p, ()):
            if s == sym:
                value = value or v
    for t in busy:
        for s, v in net.busy_outputs.get(t, ()):
            if s == sym:
                value = value or v
    return value


def step_conflicts(net: AnalysisNet, step: Sequence[int], marked: Sequence[int],
                   busy: Sequence[int]) -> list[tuple[str, list[tuple[str, str, WriteValue]]]]:
    """Symbols written to different values within one step by its transitions' actions, or
    by an action against the place-driven value of the state the step leads to (which the
    engine writes again in the next scan: the output glitches)."""
    writes: dict[str, list[tuple[str, str, WriteValue]]] = {}
    for t in step:
        for sym, value in net.actions[t]:
            writes.setdefault(sym, []).append(
                (f"transition {net.transition_names[t]}", net.where_transition(t), value))
    driven = net.driven_symbols
    out = []
    for sym, ws in sorted(writes.items()):
        entries = list(ws)
        if sym in driven:
            entries.append((f"places/running transitions driving {sym}", "",
                            moore_value(net, sym, marked, busy)))
        if len({str(v) for _, _, v in entries}) > 1:
            out.append((sym, entries))
    return out


def describe(value: WriteValue) -> str:
    return str(value) if isinstance(value, int) else f"({value})"
