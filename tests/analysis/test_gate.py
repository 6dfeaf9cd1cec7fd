"""The gate on the case studies and on the test programs with one finding each."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.analysis.gate import verify
from softplc.program.compiler import compile_file

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent / "programs"


@pytest.mark.parametrize("name", ["transport", "drilling"])
@pytest.mark.parametrize("semantics", ["scan", "interleaving"])
def test_case_studies_pass_the_gate(name: str, semantics: str) -> None:
    verdict = verify(compile_file(ROOT / "programs" / f"{name}.yaml"), semantics=semantics)
    d = verdict.analysis.to_dict()
    assert d["complete"] and d["bounded"] is True
    assert d["deadlocks"] == [] and d["output_conflicts"] == [] and d["dead_transitions"] == []
    assert not verdict.blocking, verdict.findings
    assert d["states"] > 1 and d["edges"] >= d["states"] - 1


def _finding(verdict_findings: tuple[str, ...], needle: str) -> str:
    hits = [f for f in verdict_findings if needle in f]
    assert hits, verdict_findings
    return hits[0]


def test_unbounded_place_is_found_by_covering_and_located() -> None:
    verdict = verify(compile_file(HERE / "unbounded.yaml"))
    d = verdict.analysis.to_dict()
    assert verdict.blocking and d["bounded"] is False and d["complete"]
    assert d["place_bounds"]["buffer"] is None and d["place_bounds"]["idle"] == 1
    line = _finding(verdict.findings, "place buffer: unbounded")
    assert line.startswith("tests/analysis/programs/unbounded.yaml:8: ") or \
        line.split(": ")[0].endswith("unbounded.yaml:8")
    assert "strictly covered" in line


def test_deadlock_has_its_shortest_sequence_and_location() -> None:
    verdict = verify(compile_file(HERE / "deadlock.yaml"))
    d = verdict.analysis.to_dict()
    assert d["deadlocks"] == [{"marking": {"a_half": 1, "b_half": 1},
                               "path": ["take_a+take_b"]}]
    line = _finding(verdict.findings, "deadlock")
    assert line.split(": ")[0].endswith("deadlock.yaml:11")  # a_half's line
    assert "transition a_second: dead" in " ".join(verdict.findings)
    assert verdict.blocking


def test_deadlock_in_interleaving_semantics_too() -> None:
    verdict = verify(compile_file(HERE / "deadlock.yaml"), semantics="interleaving")
    paths = [d["path"] for d in verdict.analysis.to_dict()["deadlocks"]]
    assert ["take_a", "take_b"] in paths
    assert verdict.analysis.to_dict()["dead_transitions"] == []  # each can fire alone


def test_output_conflict_is_located_at_the_writer() -> None:
    verdict = verify(compile_file(HERE / "conflict.yaml"))
    d = verdict.analysis.to_dict()
    assert [c["symbol"] for c in d["output_conflicts"]] == ["motor"]
    assert d["output_conflicts"][0]["path"] == ["split", "brake"]
    line = _finding(verdict.findings, "output motor")
    assert line.split(": ")[0].endswith("conflict.yaml:17")  # the brake transition
    assert verdict.blocking


def test_max_states_gives_an_incomplete_result_not_a_crash() -> None:
    verdict = verify(compile_file(ROOT / "programs" / "transport.yaml"), max_states=3)
    d = verdict.analysis.to_dict()
    assert d["complete"] is False and d["states"] == 3
    assert d["dead_transitions"] == []  # unknown when incomplete: not reported
    assert any("incomplete" in f for f in verdict.findings)
    assert not verdict.blocking
