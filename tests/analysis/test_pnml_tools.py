"""PNML written by other tools (tests/analysis/pnml_tools/): WoPeD's ptNetb without pages,
PIPE's "P/T net", pm4py's pnmlcoremodel (files pm4py 2.7.23 wrote), ISO ptnet with nested
pages; same-named places kept apart; empty nets and unknown types refused with the reason;
`softplc check NET.pnml`; an exported net analyses wherever it is copied.

The expected state and edge counts were worked out by hand from each drawing (comments
below); pm4py's reachability graph gave the same for the WoPeD, pm4py and transport files.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from softplc.analysis.analyze import analyze
from softplc.analysis.pnml import (
    compiled_net,
    load_for_analysis,
    parse_pnml,
    pt_analysis_net,
    read_pnml,
    structure,
)
from softplc.cli import main
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file

ROOT = Path(__file__).resolve().parents[2]
TOOLS = Path(__file__).resolve().parent / "pnml_tools"


@pytest.mark.parametrize(("name", "places", "transitions", "states", "edges", "deadlocks"), [
    # start -> register -> wait, wait (AND) -> check, check -> done A, done B -> close -> end:
    # 1 + the 2x2 diamond + 1 states.
    ("woped_ptnetb.pnml", 6, 4, 6, 6, [{"end": 1}]),
    # buffer 0..2 (capacity 2, consume takes 2) x alarmed 0/1; alarm only at buffer 0.
    ("pipe_ptnet.pnml", 4, 3, 6, 7, []),
    # source -> receive (2 items) -> pack, pack -> ship (takes 2) -> sink, or skip -> sink.
    ("pm4py_coremodel.pnml", 4, 4, 5, 5, [{"sink": 1}]),
    # mutual exclusion: both idle, 1 critical, 2 critical.
    ("iso_nested_pages.pnml", 5, 4, 3, 4, []),
])
def test_other_tools_files_are_read_whole(name: str, places: int, transitions: int,
                                          states: int, edges: int,
                                          deadlocks: list[dict[str, int]]) -> None:
    net, compiled = load_for_analysis(TOOLS / name)
    assert compiled is None
    assert (net.n_places, net.n_transitions) == (places, transitions)
    d = analyze(net, "interleaving").to_dict()
    assert (d["states"], d["edges"], d["complete"]) == (states, edges, True)
    assert [x["marking"] for x in d["deadlocks"]] == deadlocks


def test_pipe_capacity_inhibitor_and_weights_are_read() -> None:
    net, _ = load_for_analysis(TOOLS / "pipe_ptnet.pnml")
    buffer, alarm, consume = (net.place_names.index("buffer"),
                              net.transition_names.index("alarm"),
                              net.transition_names.index("consume"))
    assert net.capacity[buffer] == 2 and net.inhibit[alarm, buffer] == 1
    assert net.pre[consume, buffer] == 2 and net.initial.tolist() == [1, 0, 1, 0]
    assert any("PIPE" in n for n in net.notes)


def test_same_named_places_and_transitions_stay_distinct() -> None:
    net, _ = load_for_analysis(TOOLS / "woped_ptnetb.pnml")
    d = analyze(net, "interleaving").to_dict()
    assert list(d["place_bounds"]) == ["start", "wait [p2]", "wait [p3]", "done A", "done B",
                                       "end"]
    assert net.transition_names == ("register", "check [t2]", "check [t3]", "close")


def test_a_program_with_two_places_of_one_name_is_refused(tmp_path: Path) -> None:
    text = (TOOLS / "woped_ptnetb.pnml").read_text().replace(
        '<net type="http://www.informatik.hu-berlin.de/top/pntd/ptNetb" id="noID">',
        '<net type="http://www.informatik.hu-berlin.de/top/pntd/ptNetb" id="noID">'
        '<toolspecific tool="softplc" version="1"><program>{"io_image": "s.yaml"}</program>'
        "</toolspecific>")
    path = tmp_path / "named.pnml"
    path.write_text(text)
    with pytest.raises(ProgramError) as err:
        compiled_net(read_pnml(path))
    assert "place name 'wait' is also place 'p2'" in err.value.problems[0].message


def test_pm4py_reexport_of_an_export_is_the_same_pt_net() -> None:
    """pm4py read `softplc export programs/transport.yaml` and wrote it back (pnmlcoremodel,
    softplc's toolspecific data dropped): the same P/T skeleton; pm4py's own reachability
    graph of it had 10 states and 17 edges."""
    ours = pt_analysis_net(parse_pnml(export_of_transport(), "transport.pnml"))
    theirs, compiled = load_for_analysis(TOOLS / "pm4py_transport_reexport.pnml")
    assert compiled is None

    def arcs(net: object) -> set[tuple[str, str, int, int]]:
        return {(t, p, int(net.pre[i, j]), int(net.post[i, j]))  # type: ignore[attr-defined]
                for i, t in enumerate(net.transition_names)  # type: ignore[attr-defined]
                for j, p in enumerate(net.place_names)  # type: ignore[attr-defined]
                if net.pre[i, j] or net.post[i, j]}  # type: ignore[attr-defined]
    assert arcs(theirs) == arcs(ours)
    d = analyze(theirs, "interleaving").to_dict()
    assert (d["states"], d["edges"]) == (10, 17)


def export_of_transport() -> bytes:
    from softplc.analysis.pnml import export_compiled

    return export_compiled(compile_file(ROOT / "programs" / "transport.yaml")).encode()


PT = "http://www.pnml.org/version-2009/grammar/ptnet"
BODY = '<place id="a"><initialMarking><text>1</text></initialMarking></place>' \
       '<transition id="t"/><arc id="x" source="a" target="t"/>'


@pytest.mark.parametrize("net_type", [
    PT, PT + "#", "http://www.pnml.org/version-2009/grammar/pnmlcoremodel",
    "http://www.informatik.hu-berlin.de/top/pntd/ptNetb", "P/T net"])
@pytest.mark.parametrize("paged", [True, False])
def test_pt_types_with_and_without_pages(net_type: str, paged: bool) -> None:
    inner = f'<page id="pg">{BODY}</page>' if paged else BODY
    net = parse_pnml(f'<pnml><net id="n" type="{net_type}">{inner}</net></pnml>'.encode(),
                     "n.pnml")
    assert ([p.ident for p in net.places], [t.ident for t in net.transitions]) == (["a"], ["t"])
    assert net.arcs[0][:4] == (0, 0, 1, False)


@pytest.mark.parametrize(("net_type", "reason"), [
    ("http://www.pnml.org/version-2009/grammar/symmetricnet", "high-level and coloured"),
    ("http://example.org/mynet", "not a P/T net type"),
    (None, "not a P/T net type")])
def test_other_types_are_refused_with_the_reason(net_type: str | None, reason: str) -> None:
    attr = "" if net_type is None else f' type="{net_type}"'
    with pytest.raises(ProgramError) as err:
        parse_pnml(f'<pnml>\n<net id="n"{attr}>{BODY}</net></pnml>'.encode(), "n.pnml")
    problem = err.value.problems[0]
    assert problem.line == 2 and reason in problem.message and "ptNetb" in problem.message


@pytest.mark.parametrize("inner", ["", '<page id="p"/>', '<page id="p"><page id="q"/></page>',
                                   "<places><place id='a'/></places>"])
def test_a_net_with_no_place_and_no_transition_is_refused(inner: str) -> None:
    """It was read as empty and reported as 'deadlock at the initial marking'."""
    with pytest.raises(ProgramError) as err:
        parse_pnml(f'<pnml><net id="n" type="{PT}">{inner}</net></pnml>'.encode(), "e.pnml")
    assert "no place and no transition" in err.value.problems[0].message


@pytest.mark.parametrize(("arc_extra", "message"), [
    ("<arctype><text>reset</text></arctype>", "reset arcs are not read"),
    ('<inscription><value>Default,1,Red,2</value></inscription>', "several PIPE token classes"),
])
def test_unread_arc_kinds_are_refused(arc_extra: str, message: str) -> None:
    body = BODY.replace('<arc id="x" source="a" target="t"/>',
                        f'<arc id="x" source="a" target="t">{arc_extra}</arc>')
    with pytest.raises(ProgramError) as err:
        parse_pnml(f'<pnml><net id="n" type="{PT}">{body}</net></pnml>'.encode(), "r.pnml")
    assert message in err.value.problems[0].message


def test_pm4py_inhibitor_arc_is_read() -> None:
    body = BODY.replace('<arc id="x" source="a" target="t"/>',
                        '<arc id="x" source="a" target="t"><inscription><text>2</text>'
                        "</inscription><arctype><text>inhibitor</text></arctype></arc>")
    net = parse_pnml(f'<pnml><net id="n" type="{PT}">{body}</net></pnml>'.encode(), "i.pnml")
    assert (net.arcs, net.inhibit) == ([], [(0, 0, 2)])


def test_check_accepts_pnml(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(TOOLS / "woped_ptnetb.pnml")]) == 0
    out = capsys.readouterr().out
    assert "P/T net noID" in out and "6 places, 4 transitions, 10 arcs" in out
    assert "deadlock" in out  # the end marking, as a warning


def test_check_of_a_bad_pnml_names_the_problem(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.pnml"
    bad.write_text(f'<pnml>\n<net id="n" type="{PT}"/></pnml>')
    assert main(["check", str(bad)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}:2" in err and "no place and no transition" in err and "YAML" not in err


def _export_elsewhere(tmp_path: Path) -> tuple[Path, Path]:
    made = tmp_path / "made" / "transport.pnml"
    made.parent.mkdir()
    assert main(["export", str(ROOT / "programs" / "transport.yaml"), "-o", str(made)]) == 0
    moved = tmp_path / "elsewhere" / "deeper" / "transport.pnml"
    moved.parent.mkdir(parents=True)
    shutil.copy(made, moved)
    return made, moved


def test_an_export_copied_elsewhere_still_analyses(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """`../io_images/transport.yaml:0: cannot read symbols file` before: the symbols file
    is embedded, so the copy compiles to the same program."""
    _, moved = _export_elsewhere(tmp_path)
    _, compiled = load_for_analysis(moved)
    assert compiled is not None
    assert structure(compiled) == structure(compile_file(ROOT / "programs" / "transport.yaml"))
    capsys.readouterr()
    assert main(["analyze", str(moved), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["semantics"] == "scan"
    assert main(["check", str(moved)]) == 0


def test_without_its_io_image_a_net_is_analysed_as_pt_with_a_note(tmp_path: Path) -> None:
    _, moved = _export_elsewhere(tmp_path)
    text = moved.read_text()
    start = text.index('"io_image_text"')
    moved.write_text(text[:start] + text[text.index('"name"', start):])  # an older export
    net, compiled = load_for_analysis(moved)
    assert compiled is None and net.n_places == 8
    assert any("not found beside transport.pnml and not embedded" in n for n in net.notes)
