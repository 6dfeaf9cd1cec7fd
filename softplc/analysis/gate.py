"""The verification gate: analyse a compiled program, list located findings, block or not.

Owns: `verify(net) -> Verdict`, the one call the download path and `softplc check` make, and
the wording of each finding (`FILE:LINE: place p: unbounded ...`). Blocking findings: an
unbounded place, a deadlock, an output conflict, a dead transition. An incomplete analysis
(past max_states or a work budget) is a non-blocking finding; a net too large to analyse
(analysis/model.py MAX_CELLS) a blocking one. Does not know: HTTP, the scan, the CLI.
"""

from __future__ import annotations

from dataclasses import dataclass

from softplc.analysis.analyze import DEFAULT_MAX_STATES, Analysis, analyze
from softplc.analysis.model import AnalysisNet, TooLarge, from_compiled
from softplc.core.net import CompiledNet

GATE_MAX_STATES = 20_000


@dataclass(frozen=True, slots=True)
class Verdict:
    findings: tuple[str, ...]  # every finding, one located line each, blocking ones first
    blocking: bool
    analysis: Analysis | None  # None: the net is too large to analyse (the finding says)

    @property
    def summary(self) -> str:
        if self.analysis is None:
            return "analysis skipped (net too large for the analysis)"
        d = self.analysis.to_dict()
        bounded = {True: "bounded", False: "UNBOUNDED", None: "bounds unknown"}[d["bounded"]]
        return (f"analysis ({d['semantics']}): {d['states']} states, {d['edges']} edges"
                f"{'' if d['complete'] else ' (incomplete)'}, {bounded}, "
                f"{d['deadlock_count']} deadlock(s), {len(d['dead_transitions'])} dead "
                f"transition(s), {len(d['output_conflicts'])} output conflict(s), "
                f"{d['seconds'] * 1000:.1f} ms")


def verify(net: CompiledNet, max_states: int = GATE_MAX_STATES,
           semantics: str = "scan") -> Verdict:
    """Analyse `net` under the PLC's scan semantics (any input at any scan). A net too large
    for the analysis is one blocking finding: what was not verified is not accepted under
    --verify refuse (as the download gate's transition bound, runtime/prepare.py)."""
    try:
        model = from_compiled(net)
    except TooLarge as exc:
        return Verdict((str(exc),), True, None)
    return verdict_of(analyze(model, semantics, max_states), gate=True)


def verdict_of(result: Analysis, gate: bool = False) -> Verdict:
    """The findings of `result`; `gate`: it ran on check's budget (GATE_MAX_STATES)."""
    net, g = result.net, result.graph
    blocking: list[str] = []
    for u in g.unbounded:
        blocking.append(f"{net.where_place(u.place)}: place {net.place_names[u.place]}: "
                        f"unbounded: {u.witness}")
    for d in g.deadlocks:
        blocking.append(f"{_deadlock_where(net, d.marking)}: deadlock: marking "
                        f"{_marking(d.marking)} reached by {_seq(d.path)}; no transition "
                        "can ever fire there")
    if g.deadlock_count > len(g.deadlocks):
        blocking.append(f"{net.where_net()}: {g.deadlock_count - len(g.deadlocks)} more "
                        "deadlock(s) not listed")
    for t in result.dead_transitions:
        blocking.append(f"{net.where_transition(t)}: transition {net.transition_names[t]}: "
                        "dead (fires in no reachable state)")
    for c in g.conflicts:
        where = c.locations[0] if c.locations else net.where_net()
        blocking.append(f"{where}: output {c.symbol}: driven to different values "
                        f"({'; '.join(c.drivers)}) after {_seq(c.path)}")
    notes: list[str] = []
    if not g.complete:
        why = g.stopped or (f"explored {g.states:,} states (check's budget; `softplc analyze` "
                            f"explores up to {DEFAULT_MAX_STATES:,})" if gate else
                            f"stopped at {g.states:,} states (--max-states)")
        notes.append(f"{net.where_net()}: analysis incomplete: {why}; findings so far only")
    return Verdict(tuple(blocking + notes), bool(blocking), result)


def _seq(path: tuple[str, ...]) -> str:
    return " ; ".join(path) if path else "(the initial marking)"


def _marking(marking: dict[str, int]) -> str:
    return "{" + ", ".join(f"{k}: {v}" for k, v in marking.items()) + "}"


def _deadlock_where(net: AnalysisNet, marking: dict[str, int]) -> str:
    for p, name in enumerate(net.place_names):
        if name in marking:
            return net.where_place(p)
    return net.where_net()
