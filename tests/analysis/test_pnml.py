"""PNML: export then import gives back the same compiled net; bad PNML gets located errors;
the XML parser refuses entity expansion and external entities."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softplc.analysis.analyze import analyze
from softplc.analysis.model import from_compiled
from softplc.analysis.models import kanban
from softplc.analysis.pnml import (
    compiled_net,
    export_compiled,
    export_pt,
    load_for_analysis,
    parse_pnml,
    read_pnml,
    structure,
)
from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file, compile_text

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = Path(__file__).resolve().parent / "programs"


def _round_trip(net: CompiledNet, folder: Path) -> CompiledNet:
    out = folder / f"{net.name}.pnml"
    io_ref = os.path.relpath(Path(net.io.path).resolve(), folder.resolve())
    out.write_text(export_compiled(net, io_image=io_ref), encoding="utf-8")
    return compiled_net(read_pnml(out))


@pytest.mark.parametrize("name", ["transport", "drilling"])
def test_case_studies_round_trip(name: str, tmp_path: Path) -> None:
    net = compile_file(ROOT / "programs" / f"{name}.yaml")
    back = _round_trip(net, tmp_path)
    assert structure(back) == structure(net)
    assert back.place_where[0] == (str(tmp_path / f"{name}.pnml"), 7)


GUARDS = [None, "go", "not sensor", "go and not sensor", "rising(go)"]
ACTIONS = ["set lamp", "reset lamp", "pulse lamp", "count = 3"]


@st.composite
def programs(draw: st.DrawFn) -> str:
    n_places = draw(st.integers(1, 5))
    places = {}
    for i in range(n_places):
        spec: dict[str, object] = {"tokens": draw(st.integers(0, 2))}
        if draw(st.booleans()):
            spec["capacity"] = spec["tokens"] + draw(st.integers(0, 2))  # type: ignore[operator]
        if draw(st.booleans()):
            spec["outputs"] = {"motor": 1}
        places[f"p{i}"] = spec
    names = list(places)
    transitions = {}
    for i in range(draw(st.integers(1, 5))):
        arc = st.sampled_from(names)
        spec = {"from": draw(st.lists(arc, min_size=1, max_size=2)),
                "to": draw(st.lists(arc, max_size=2)),
                "priority": draw(st.integers(0, 2))}
        if draw(st.booleans()):
            spec["read"] = [{"place": draw(arc), "weight": draw(st.integers(1, 2))}]
        if draw(st.booleans()):
            spec["inhibit"] = [{"place": draw(arc), "weight": draw(st.integers(1, 2))}]
        guard = draw(st.sampled_from(GUARDS))
        if guard:
            spec["when"] = guard
        if draw(st.booleans()):
            spec["do"] = draw(st.lists(st.sampled_from(ACTIONS), max_size=2))
        timing = draw(st.sampled_from([None, "delay", "duration"]))
        if timing:
            spec[timing] = f"{draw(st.integers(1, 500))}ms"
            if timing == "duration" and draw(st.booleans()):
                spec["outputs"] = {"lamp": 1}
        transitions[f"t{i}"] = spec
    return json.dumps({"program": "gen", "io_image": "symbols.yaml", "places": places,
                       "transitions": transitions, "events": ["tick"]})


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(programs())
def test_round_trip_property(tmp_path: Path, text: str) -> None:
    try:
        net = compile_text(text, str(PROGRAMS / "gen.yaml"))
    except ProgramError:
        return  # an invalid random program (e.g. initial tokens over capacity): not exported
    back = _round_trip(net, tmp_path)
    assert structure(back) == structure(net)
    # and the analysis sees the same net both ways (bounded: a random net may grow without
    # a provable covering, e.g. past an inhibitor arc)
    a = analyze(from_compiled(net), max_states=300)
    b = analyze(from_compiled(back), max_states=300)
    assert (a.graph.states, a.graph.edges) == (b.graph.states, b.graph.edges)


def test_bare_pnml_pages_and_references(tmp_path: Path) -> None:
    text = b"""<?xml version="1.0"?>
<pnml xmlns="http://www.pnml.org/version-2009/grammar/pnml">
 <net id="n" type="http://www.pnml.org/version-2009/grammar/ptnet">
  <page id="top">
   <place id="a"><name><text>ready</text></name>
     <initialMarking><text>2</text></initialMarking></place>
   <transition id="t"><name><text>go</text></name></transition>
   <page id="sub">
    <referencePlace id="ra" ref="a"/>
    <referencePlace id="rra" ref="ra"/>
    <place id="b"/>
    <referenceTransition id="rt" ref="t"/>
    <arc id="x1" source="rra" target="rt"><inscription><text>2</text></inscription></arc>
    <arc id="x2" source="rt" target="b"/>
   </page>
  </page>
 </net>
</pnml>"""
    path = tmp_path / "n.pnml"
    path.write_bytes(text)
    net, compiled = load_for_analysis(path)
    assert compiled is None and net.place_names == ("ready", "b")
    d = analyze(net, "interleaving").to_dict()
    assert d["states"] == 2 and d["edges"] == 1 and d["deadlocks"][0]["path"] == ["go"]
    assert d["deadlocks"][0]["marking"] == {"b": 1}


def test_kanban_pnml_matches_the_generator(tmp_path: Path) -> None:
    path = tmp_path / "k.pnml"
    path.write_text(export_pt(kanban(1)), encoding="utf-8")
    net, _ = load_for_analysis(path)
    assert analyze(net, "interleaving").to_dict()["states"] == 160


@pytest.mark.parametrize(("body", "line", "message"), [
    (b'<pnml><net id="n" type="http://www.pnml.org/version-2009/grammar/ptnet"><page id="p">\n'
     b'<place id="a"/>\n<arc id="x" source="a" target="zz"/>\n</page></net></pnml>', 3,
     "must be a place and a transition"),
    (b'<pnml><net id="n" type="http://www.pnml.org/version-2009/grammar/ptnet"><page id="p">\n'
     b'<place id="a"><initialMarking><text>-1</text></initialMarking></place>\n</page></net>'
     b"</pnml>", 2, "initial marking"),
    (b'<pnml><net id="n" type="http://www.pnml.org/version-2009/grammar/ptnet"><page id="p">\n'
     b'<place id="a"/>\n<place id="a"/>\n</page></net></pnml>', 3, "used twice"),
    (b"<pnml><net>\n<page>\n</net></pnml>", 3, "not well-formed"),
    (b'<pnml><net id="n" type="http://www.pnml.org/version-2009/grammar/pt"><page id="p">'
     b"</page></net></pnml>", 1, "only P/T nets"),
])
def test_bad_pnml_is_located(body: bytes, line: int, message: str) -> None:
    with pytest.raises(ProgramError) as err:
        parse_pnml(body, "bad.pnml")
    problem = err.value.problems[0]
    assert (problem.file, problem.line) == ("bad.pnml", line)
    assert message in problem.message


def test_entity_expansion_is_refused() -> None:
    bomb = (b'<?xml version="1.0"?>\n<!DOCTYPE pnml [\n<!ENTITY a "aaaaaaaaaa">\n'
            b'<!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">\n]>\n<pnml>&b;</pnml>')
    with pytest.raises(ProgramError) as err:
        parse_pnml(bomb, "bomb.pnml")
    assert "refused XML" in err.value.problems[0].message


def test_external_entity_is_refused(tmp_path: Path) -> None:
    secret = tmp_path / "secret.txt"
    secret.write_text("do not read me")
    doc = (f'<?xml version="1.0"?>\n<!DOCTYPE pnml [\n<!ENTITY x SYSTEM "file://{secret}">\n]>'
           "\n<pnml><net>&x;</net></pnml>").encode()
    with pytest.raises(ProgramError) as err:
        parse_pnml(doc, "ext.pnml")
    assert "refused XML" in err.value.problems[0].message
