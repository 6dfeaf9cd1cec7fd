"""A PNML export is the same net in other tools (issue 39): capacities as complement places,
read arcs as pairs of arcs, inhibitor arcs on a place with a capacity as a read of its
complement; an inhibitor arc P/T cannot say is named in a warning (analysis/pnml_encode.py,
docs/analysis.md "PNML"). The exported skeleton, read back by softplc's PNML reader as a bare
P/T net (what another tool sees) and by pm4py when it is installed, has as many reachable
states as softplc's own analysis of the program's skeleton with those constructs."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from softplc.analysis.analyze import analyze
from softplc.analysis.model import AnalysisNet, from_compiled, from_pt
from softplc.analysis.pnml import compiled_net, pt_analysis_net, read_pnml, structure
from softplc.cli import main
from softplc.program.compiler import compile_file

ROOT = Path(__file__).resolve().parents[2]

GUARDED = """io_image: io.yaml
places:
  a: {tokens: 3}
  b: {capacity: 2}
  c: {}
  d: {tokens: 1}
transitions:
  put: {from: [a], to: [b], read: {d: 1}}
  take: {from: [b], to: [c], inhibit: {d: 1}}
  back: {from: [c], to: [a], inhibit: {b: 2}}
  toggle: {from: [d, a], to: [d, c]}
  untoggle: {from: [c], to: [d], inhibit: {c: 3}}
"""
IO = 'symbols:\n  x: {address: "%IX0.0", type: bool}\n'


def skeleton(path: Path) -> AnalysisNet:
    """softplc's own view of the program's P/T part: arcs, read and inhibitor arcs,
    capacities; guards, timing and priorities left out (no P/T tool has them)."""
    c = from_compiled(compile_file(path))
    pt = from_pt(c.name, c.source, [(n, int(k), 1) for n, k in zip(c.place_names, c.initial,
                                                                   strict=True)],
                 [(n, 1) for n in c.transition_names], c.pre, c.post, c.inhibit, c.test)
    return dataclasses.replace(pt, capacity=c.capacity.copy())


def states(net: AnalysisNet) -> tuple[int, bool | None]:
    d = analyze(net, "interleaving", 100_000).to_dict()
    assert d["complete"]
    return d["states"], d["bounded"]


def export(program: Path, out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    assert main(["export", str(program), "-o", str(out)]) == 0
    return capsys.readouterr().err


def test_cell_exports_as_the_same_bounded_net(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    program = ROOT / "programs" / "cell.yaml"
    out = tmp_path / "cell.pnml"
    assert export(program, out, capsys) == ""  # nothing P/T cannot say
    theirs = states(pt_analysis_net(read_pnml(out)))
    assert theirs == states(skeleton(program)) == (34, True)  # before: unbounded
    assert structure(compiled_net(read_pnml(out))) == structure(compile_file(program))


def test_inhibitor_arcs_encoded_where_exact_and_warned_where_not(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "io.yaml").write_text(IO)
    program = tmp_path / "p.yaml"
    program.write_text(GUARDED)
    out = tmp_path / "p.pnml"
    warned = export(program, out, capsys)
    # b has a capacity: `back` is exact; d and c have none: `take` and `untoggle` are named
    assert warned.splitlines() == [
        f"warning: {program}: transition {t}: inhibitor arc from {p} (weight {w}) has no P/T "
        "form (the place has no capacity): other tools see the transition without it "
        "(softplc's toolspecific data keeps it)" for t, p, w in (("take", "d", 1),
                                                                 ("untoggle", "c", 3))]
    assert structure(compiled_net(read_pnml(out))) == structure(compile_file(program))
    program.write_text(GUARDED.replace("d: {tokens: 1}", "d: {tokens: 1, capacity: 1}")
                       .replace("c: {}", "c: {capacity: 4}"))
    assert export(program, out, capsys) == ""
    theirs = states(pt_analysis_net(read_pnml(out)))
    assert theirs == states(skeleton(program)) and theirs[1] is True
    assert structure(compiled_net(read_pnml(out))) == structure(compile_file(program))
