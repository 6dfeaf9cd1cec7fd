"""The analysis under budgets (issue 28): invariants that cannot explode, an exploration that
stops with a reason, nets too large for the dense arrays refused before any is allocated,
PNML nesting bounded. Each case is bounded in time: a real `softplc analyze` process with a
timeout where the old code never finished."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from softplc.analysis.analyze import Analysis, analyze
from softplc.analysis.explore import explore
from softplc.analysis.gate import verdict_of, verify
from softplc.analysis.invariants import p_invariants
from softplc.analysis.model import MAX_CELLS, TooLarge, from_pt
from softplc.analysis.models import PtNet, analysis_net, philosophers
from softplc.analysis.pnml import export_pt, parse_pnml
from softplc.core.problems import ProgramError
from softplc.core.xmltree import MAX_DEPTH
from softplc.program.compiler import compile_text

ROOT = Path(__file__).resolve().parents[2]
Arcs = dict[str, int]


def _ring(tag: str, stages: int, width: int, marked: bool = True, twins: int = 0
          ) -> tuple[list[tuple[str, int]], list[tuple[str, Arcs, Arcs]]]:
    """A ring of fork-join stages: `width` parallel places per stage, one transition from each
    stage to the next (and `twins` stages with a second, identical one). Its minimal
    P-invariants pick one place per stage: width ** stages of them."""
    places = [(f"{tag}{i}_{w}", int(marked and i == 0)) for i in range(stages)
              for w in range(width)]
    trans: list[tuple[str, Arcs, Arcs]] = []
    for i in range(stages):
        pre = {f"{tag}{i}_{w}": 1 for w in range(width)}
        post = {f"{tag}{(i + 1) % stages}_{w}": 1 for w in range(width)}
        trans.append((f"{tag}t{i}", pre, post))
        if i < twins:
            trans.append((f"{tag}u{i}", dict(pre), dict(post)))
    return places, trans


def fork_join_253() -> PtNet:
    """253 places, 178 transitions, 2,530 reachable states: the size of the public benchmark
    net whose P-invariants never finished (3 ** 46 * 2 ** 55 minimal ones), built alike."""
    a_places, a_trans = _ring("a", 46, 3, twins=46)
    b_places, b_trans = _ring("b", 55, 2, twins=31)
    idle, _ = _ring("c", 5, 1, marked=False)
    return PtNet("forkjoin253", tuple(a_places + b_places + idle), tuple(a_trans + b_trans))


def test_the_fork_join_net_has_the_benchmark_size() -> None:
    net = fork_join_253()
    assert (len(net.places), len(net.transitions)) == (253, 178)


def test_analyze_of_a_253_place_net_finishes_in_seconds(tmp_path: Path) -> None:
    path = tmp_path / "forkjoin253.pnml"
    path.write_text(export_pt(fork_join_253()), encoding="utf-8")
    began = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "softplc.cli", "analyze", str(path), "--json"],
                         capture_output=True, text=True, timeout=20, check=False, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    assert (d["states"], d["complete"], d["bounded"]) == (2530, True, True)
    assert d["invariants_complete"] is False
    assert any("P-invariants incomplete" in n for n in d["notes"]), d["notes"]
    assert time.monotonic() - began < 20


def test_incomplete_invariants_are_still_invariants() -> None:
    net = analysis_net(fork_join_253())
    began = time.monotonic()
    pinv = p_invariants(net.pre, net.post)
    assert time.monotonic() - began < 15
    assert not pinv.complete and "budget" in pinv.why
    incidence = (net.post - net.pre).T
    assert pinv.vectors  # some found, each one a semi-positive invariant
    for v in pinv.vectors:
        y = np.array(v)
        assert (y >= 0).all() and y.any() and not (y @ incidence).any()


def test_complete_invariants_are_unchanged_on_a_small_net() -> None:
    net = analysis_net(philosophers(5))
    pinv = p_invariants(net.pre, net.post)
    assert pinv.complete and pinv.why == "" and len(pinv.vectors) == 10


def test_unknown_conservativeness_is_not_reported_as_false() -> None:
    d = analyze(analysis_net(fork_join_253()), "interleaving").to_dict()
    covered = {p for v in d["p_invariants"] for p in v}
    assert len(covered) < 253 and d["conservative"] is None


def test_exploration_past_its_work_budget_stops_with_the_reason() -> None:
    net = analysis_net(philosophers(10))
    graph = explore(net, "interleaving", 10**6, max_work=500)
    assert not graph.complete and "work budget" in graph.stopped
    assert graph.deadlock_count == 0  # a state cut short is no deadlock


def test_the_gate_names_the_work_budget() -> None:
    net = analysis_net(philosophers(10))
    pinv = p_invariants(net.pre, net.post)
    graph = explore(net, "interleaving", 20_000, max_work=50)
    findings = verdict_of(Analysis(net, graph, pinv, pinv, 0.0)).findings
    assert any(f.endswith("analysis incomplete: stopped after 50 candidate sets and ancestors "
                          "(work budget); findings so far only") for f in findings), findings


def _too_large_places() -> int:
    return MAX_CELLS // 2_000 + 1


def test_a_net_over_the_cell_bound_is_refused_before_allocating() -> None:
    P, T = 100_000, 100_000  # the net: numpy asked for 74.5 GiB per array
    with pytest.raises(TooLarge, match=r"100,000 places x 100,000 transitions .* analysis "
                                       r"bound of 4,000,000"):
        from_pt("huge", "huge.pnml", [(f"p{i}", 0, 1) for i in range(P)],
                [(f"t{i}", 1) for i in range(T)], np.zeros((1, 1), np.int64),
                np.zeros((1, 1), np.int64))


def test_the_gate_refuses_a_net_over_the_cell_bound_as_one_finding() -> None:
    places = _too_large_places()  # x 2,000 transitions: just over the bound
    lines = ["program: wide", "io_image: ../io_images/transport.yaml", "places:",
             "  p0: {tokens: 1}"] + [f"  p{i}: {{}}" for i in range(1, places)]
    lines += ["transitions:"] + [f"  t{i}: {{from: [p{i}], to: [p{(i + 1) % 2000}]}}"
                                 for i in range(2000)]
    net = compile_text("\n".join(lines) + "\n", str(ROOT / "programs" / "wide.yaml"), ROOT)
    began = time.monotonic()
    verdict = verify(net)
    assert time.monotonic() - began < 5
    assert verdict.blocking and verdict.analysis is None
    assert verdict.summary == "analysis skipped (net too large for the analysis)"
    (finding,) = verdict.findings
    assert finding.startswith("programs/wide.yaml:1: not analysed: ")
    assert f"{places:,} places x 2,000 transitions" in finding and "4,000,000" in finding


def test_softplc_analyze_of_a_too_large_pnml_says_so_without_a_traceback(
        tmp_path: Path) -> None:
    places = [(f"p{i}", int(i == 0)) for i in range(20_000)]
    trans = tuple((f"t{i}", {f"p{i}": 1}, {f"p{i + 1}": 1}) for i in range(201))
    path = tmp_path / "wide.pnml"
    path.write_text(export_pt(PtNet("wide", tuple(places), trans)), encoding="utf-8")
    out = subprocess.run([sys.executable, "-m", "softplc.cli", "analyze", str(path)],
                         capture_output=True, text=True, timeout=20, check=False, cwd=ROOT)
    assert out.returncode == 1
    assert "Traceback" not in out.stderr
    assert "not analysed: 20,000 places x 201 transitions = 4,020,000 cells exceed the " \
           "analysis bound of 4,000,000" in out.stderr


def test_deeply_nested_pnml_pages_are_a_located_problem() -> None:
    n = 100_000
    data = ('<?xml version="1.0"?>\n<pnml><net id="n" type="http://www.pnml.org/version-2009/'
            'grammar/ptnet">\n' + '<page id="p">' * n + "</page>" * n + "</net></pnml>")
    began = time.monotonic()
    with pytest.raises(ProgramError) as refused:
        parse_pnml(data.encode(), "deep.pnml")
    assert time.monotonic() - began < 5
    (problem,) = refused.value.problems
    assert (problem.file, problem.line) == ("deep.pnml", 3)  # where the pages start
    assert problem.message == f"XML nested deeper than {MAX_DEPTH} elements"


def test_pages_nested_within_the_bound_are_all_read() -> None:
    depth = MAX_DEPTH - 6  # pnml, net, the pages, place, name, text
    data = ('<pnml><net id="n" type="http://www.pnml.org/version-2009/grammar/ptnet">'
            + '<page id="p">' * depth + '<place id="deep"><name><text>deep</text></name>'
            '</place>' + "</page>" * depth + "</net></pnml>")
    net = parse_pnml(data.encode(), "deep.pnml")
    assert [p.name for p in net.places] == ["deep"]
