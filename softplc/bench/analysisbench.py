"""Benchmark section `analysis`: state-space exploration speed against SNAKES' StateGraph on
the same nets in the same run, Kanban N = 5 in full, memory per state, the case studies.

Owns: the nets measured, the section's keys (`vs_snakes_states_per_s`, `kanban5_s`,
`bytes_per_state`, `case_studies_ms`, ...). Quick mode skips Kanban 5 (it measures Kanban 4,
454,475 states, as `kanban4_s`) and runs SNAKES on Kanban 2 and FMS 2 only (~6 s; the
full run adds Kanban 3, ~65 s of SNAKES).
Does not know: how the exploration works (softplc/analysis).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from softplc.analysis.analyze import analyze
from softplc.analysis.gate import verify
from softplc.analysis.models import KANBAN_STATES, PtNet, analysis_net, fms, kanban, philosophers
from softplc.bench.measure import Progress
from softplc.program.compiler import compile_file

ROOT = Path(__file__).resolve().parents[2]


def _snakes_net(net: PtNet) -> Any:
    from snakes.nets import MultiArc, PetriNet, Place, Transition, Value, dot  # type: ignore[import-untyped]

    def arc(w: int) -> Any:
        return Value(dot) if w == 1 else MultiArc([Value(dot)] * w)

    pn = PetriNet(net.name)
    for name, k in net.places:
        pn.add_place(Place(name, [dot] * k))
    for t, pre, post in net.transitions:
        pn.add_transition(Transition(t))
        for p, w in pre.items():
            pn.add_input(p, t, arc(w))
        for p, w in post.items():
            pn.add_output(p, t, arc(w))
    return pn


def snakes_states(net: PtNet) -> tuple[int, float]:
    from snakes.nets import StateGraph

    began = time.perf_counter()
    graph = StateGraph(_snakes_net(net))
    graph.build()
    return len(graph), time.perf_counter() - began


def ours(net: PtNet) -> tuple[int, int, float, float]:
    began = time.perf_counter()
    result = analyze(analysis_net(net), "interleaving", 10**8)
    return (result.graph.states, result.graph.edges, time.perf_counter() - began,
            result.graph.bytes_per_state)


def run(quick: bool, progress: Progress) -> dict[str, Any]:
    # Nets of a few thousand states and more: on smaller ones fixed costs (invariants, numpy
    # set-up, ~1 ms) hide the exploration speed being compared.
    nets = [kanban(2), fms(2)] if quick else [kanban(2), fms(2), philosophers(10), kanban(3)]
    rows = []
    snakes_states_total, snakes_s, ours_s = 0, 0.0, 0.0
    for net in nets:
        progress(f"analysis: {net.name} on SNAKES StateGraph and on softplc")
        s_states, s_time = snakes_states(net)
        o_states, o_edges, o_time, _ = ours(net)
        if s_states != o_states:
            raise AssertionError(f"{net.name}: SNAKES {s_states} states, softplc {o_states}")
        rows.append({"net": net.name, "states": o_states, "edges": o_edges,
                     "snakes_s": round(s_time, 4), "softplc_s": round(o_time, 4),
                     "ratio": round(s_time / o_time, 1)})
        snakes_states_total += s_states
        snakes_s += s_time
        ours_s += o_time
    n = 4 if quick else 5
    progress(f"analysis: Kanban N = {n}, full reachability graph")
    k_states, k_edges, k_time, k_bytes = ours(kanban(n))
    if k_states != KANBAN_STATES[n]:
        raise AssertionError(f"kanban {n}: {k_states} states, published {KANBAN_STATES[n]}")
    cases = {}
    for name in ("transport", "drilling"):
        program = compile_file(ROOT / "programs" / f"{name}.yaml")
        verify(program)  # warm (imports, first numpy calls)
        began = time.perf_counter()
        for _ in range(20):
            verdict = verify(program)
        cases[name] = round((time.perf_counter() - began) / 20 * 1000, 3)
        assert verdict.analysis is not None, f"{name}: not analysed"  # a shipped program fits
        cases[f"{name}_states"] = verdict.analysis.graph.states
    return {
        "nets": rows,
        "snakes_states_per_s": round(snakes_states_total / snakes_s, 1),
        "softplc_states_per_s": round(snakes_states_total / ours_s, 1),
        "vs_snakes_states_per_s": round(snakes_s / ours_s, 1),
        f"kanban{n}_s": round(k_time, 3),
        f"kanban{n}_states": k_states,
        f"kanban{n}_edges": k_edges,
        f"kanban{n}_states_per_s": round(k_states / k_time),
        "bytes_per_state": k_bytes,
        "case_studies_ms": cases,
    }
