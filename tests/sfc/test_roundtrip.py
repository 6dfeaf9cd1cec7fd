"""A chart read from PLCopen XML and exported goes back to the same chart (issue 42.4): every
example chart (and one with every qualifier) exported, read back with softplc's reader and
compiled is the same net, runs the same trace scan by scan (and the same as the reference
interpreter), keeps its drawing (each object's position and size, each connection's routing
points) and has the tc6_0201 shape the editors read. An edited chart or another net is never
written as if it were the chart."""

from __future__ import annotations

import random
import re
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

import defusedxml.ElementTree as DET  # type: ignore[import-untyped]
import pytest

from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.core.xmltree import Node, parse_xml
from softplc.program.compiler import compile_file
from softplc.sfc.export import export_plcopen
from softplc.sfc.model import Chart
from softplc.sfc.reader import read_chart
from softplc.sfc.writechart import write_chart
from tests.core.helpers import Bench
from tests.sfc.chartxml import ChartSpec, chart_xml
from tests.sfc.compare import compare

ROOT = Path(__file__).parents[2]
CHARTS = sorted([*(ROOT / "tests/sfc/examples").glob("*.xml"), ROOT / "programs/drilling_sfc.xml"])
QUALIFIERS = ChartSpec(
    ["Idle", "A", "B", "C"], ["Idle"],
    [(["Idle"], ["A", "B"], "go"), (["A"], ["C"], "x AND NOT stop"),
     (["B", "C"], ["Idle"], "stop OR y")],
    [("Idle", "R", "held"), ("A", "S", "held"), ("A", "L@T#30ms", "l"), ("A", "D@T#20ms", "d"),
     ("B", "DS@T#20ms", "ds"), ("B", "SD@T#20ms", "sd"), ("C", "SL@T#30ms", "sl"),
     ("Idle", "R", "sd"), ("Idle", "R", "ds"), ("Idle", "R", "sl"), ("C", "P", "p"),
     ("C", "P0", "p0"), ("B", "P1", "bump"), ("C", "N", "count")],
    {"go": ("BOOL", "%IX0.0"), "x": ("BOOL", "%IX0.1"), "y": ("BOOL", "%IX0.2"),
     "stop": ("BOOL", "%IX0.3"), "held": ("BOOL", "%QX0.0"), "l": ("BOOL", "%QX0.1"),
     "d": ("BOOL", "%QX0.2"), "ds": ("BOOL", "%QX0.3"), "sd": ("BOOL", "%QX0.4"),
     "sl": ("BOOL", "%QX0.5"), "p": ("BOOL", "%QX0.6"), "p0": ("BOOL", "%QX0.7"),
     "n": ("INT", "%QW1"), "m": ("DINT", "")},
    {"bump": "n := n + 1;", "count": "m := m + 2;"})


def _chart(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    if request.param == "qualifiers":
        path = tmp_path / "qualifiers.xml"
        path.write_text(chart_xml(QUALIFIERS), encoding="utf-8")
        return path
    return Path(request.param)


@pytest.fixture(params=[*CHARTS, "qualifiers"], ids=lambda p: Path(str(p)).name)
def chart(request: pytest.FixtureRequest, tmp_path: Path) -> Path:
    return _chart(request, tmp_path)


def exported(path: Path, directory: Path) -> Path:
    """The chart compiled, exported, written beside a copy of its FILE.io.yml (drivers)."""
    out = directory / "back" / path.name
    out.parent.mkdir()
    out.write_text(export_plcopen(compile_file(path), compile_file), encoding="utf-8")
    if (sidecar := path.with_suffix(".io.yml")).is_file():
        shutil.copy(sidecar, out.with_suffix(".io.yml"))
    return out


def test_the_chart_goes_out_and_back_to_the_same_net(chart: Path, tmp_path: Path) -> None:
    first, second = compile_file(chart), compile_file(exported(chart, tmp_path))
    assert first.place_names == second.place_names
    assert [replace(t, line=0) for t in first.transitions] == \
        [replace(t, line=0) for t in second.transitions]
    assert first.order == second.order and first.place_outputs == second.place_outputs
    assert list(first.initial) == list(second.initial)
    assert {n: (str(s.address), s.type, s.init_raw) for n, s in first.io.symbols.items()} == \
        {n: (str(s.address), s.type, s.init_raw) for n, s in second.io.symbols.items()}


def _trace(net: CompiledNet, scans: list[dict[str, int]]) -> list[object]:
    bench, out = Bench(net), list[object]()
    watched = [n for n, s in net.io.symbols.items() if not str(s.address).startswith("%I")]
    for k, values in enumerate(scans, start=1):
        bench.set(**values)
        bench.scan(k * 10_000_000)
        out.append((sorted(p for p, n in bench.marking().items() if n),
                    [bench.get(n) for n in watched]))
    return out


def test_the_exported_chart_runs_the_same_trace(chart: Path, tmp_path: Path) -> None:
    back = exported(chart, tmp_path)
    first, second = compile_file(chart), compile_file(back)
    rng = random.Random(chart.name)
    inputs = {n: s.type.value for n, s in first.io.symbols.items()
              if str(s.address).startswith("%I")}
    scans = [{n: rng.random() < 0.4 if t == "bool" else rng.randrange(20)
              for n, t in inputs.items()} for _ in range(80)]
    scans = [{n: int(v) for n, v in s.items()} for s in scans]
    steps = _trace(first, scans)
    assert len({str(s[0]) for s in steps}) > 1, "the inputs moved the chart nowhere"
    assert _trace(second, scans) == steps
    assert compare(back, scans) is None  # and the reference interpreter reads it alike


def drawing(path: Path) -> dict[str, object]:
    """Every drawn object by localId: tag, position, size, each pin's relPosition and each
    connection's routing points, a comment's text (CODESYS's inVariables feeding conditions
    are left out: the export writes their ST inline)."""
    sfc = next(n for n in parse_xml(path.read_bytes(), str(path)).walk() if n.tag == "SFC")

    def xy(n: Node | None) -> tuple[float, float] | None:
        return None if n is None else (float(n.attrs["x"]), float(n.attrs["y"]))

    def pins(n: Node) -> list[object]:
        return [(p.tag, xy(p.child("relPosition")),
                 [(c.attrs.get("refLocalId"), [xy(q) for q in c.all("position")])
                  for c in p.all("connection")])
                for p in n.children if p.tag.startswith("connectionPoint")]

    return {n.attrs["localId"]: (n.tag, xy(n.child("position")), n.attrs.get("width"),
                                 n.attrs.get("height"), pins(n),
                                 [(a.attrs.get("localId"), xy(a.child("relPosition")), pins(a))
                                  for a in n.all("action")],
                                 (n.child("content") or Node("", {}, 0)).all_text().strip())
            for n in sfc.children if n.tag != "inVariable"}


def test_the_drawing_and_the_routing_points_read_back_equal(chart: Path,
                                                            tmp_path: Path) -> None:
    first, second = drawing(chart), drawing(exported(chart, tmp_path))
    assert second == first
    if chart.name == "beremiz_counter.xml":
        routed = [c for o in first.values() for p in o[4] for c in p[2] if c[1]]  # type: ignore[index, union-attr]
        assert routed, "the example draws routing points"


XHTML = "{http://www.w3.org/1999/xhtml}p"
ORDER = {"step": ["position", "connectionPointIn", "connectionPointOut",
                  "connectionPointOutAction"],
         "transition": ["position", "connectionPointIn", "connectionPointOut", "condition"],
         "actionBlock": ["position", "connectionPointIn", "action"],
         "jumpStep": ["position", "connectionPointIn"],
         "pou": ["interface", "actions", "transitions", "body"],
         "project": ["fileHeader", "contentHeader", "types", "instances"]}


def _order(el: DET.Element, tag: str, ns: str) -> list[str]:
    seen = [ORDER[tag].index(c.tag.removeprefix(ns)) for c in el
            if c.tag.removeprefix(ns) in ORDER[tag]]
    if seen != sorted(seen) or len(seen) != len(list(el)):
        return [f"<{tag}> children {[c.tag for c in el]}"]
    return []


def tc6_0201_problems(text: str) -> list[str]:
    """What in the text is not of the tc6_0201 shape Beremiz writes and reads (XSD facts in
    ../shared/reference/plcopen-sfc.md: element order, required attributes, wiring)."""
    ns = "{http://www.plcopen.org/xml/tc6_0201}"
    root, out = DET.fromstring(text), list[str]()
    if root.tag != ns + "project":
        return [f"root {root.tag}"]
    for el in root.iter():
        if not el.tag.startswith(ns) and el.tag != XHTML:
            out.append(f"{el.tag} outside the tc6_0201 and xhtml namespaces")
        tag = el.tag.removeprefix(ns)
        if tag in ("pou", "project"):
            out += _order(el, tag, ns)
        if tag == "ST" and (len(el) != 1 or el[0].tag != XHTML):
            out.append("an ST body not in one xhtml:p")
    sfc = root.find(f"{ns}types/{ns}pous/{ns}pou/{ns}body/{ns}SFC")
    if sfc is None:
        return [*out, "no types/pous/pou/body/SFC"]
    ids = [el.get("localId") for el in sfc]
    if len(set(ids)) != len(ids) or not all(i and i.isdigit() for i in ids):
        out.append(f"localIds not unique unsignedLongs: {ids}")
    steps = {el.get("name") for el in sfc if el.tag == ns + "step"}
    for el in sfc:
        if (tag := el.tag.removeprefix(ns)) in ORDER:
            out += _order(el, tag, ns)
    for el in sfc.iter():
        ref = el.get("refLocalId")
        if el.tag == ns + "connection" and ref not in ids:
            out.append(f"connection to {ref}: no such object")
        if el.tag == ns + "jumpStep" and el.get("targetName") not in steps:
            out.append(f"jump to {el.get('targetName')}: no such step")
        if el.tag == ns + "action" and el.get("qualifier") is None:
            out.append("an action without its qualifier")
    return out


def test_the_written_xml_has_the_tc6_0201_shape(chart: Path, tmp_path: Path) -> None:
    assert tc6_0201_problems(exported(chart, tmp_path).read_text(encoding="utf-8")) == []
    assert tc6_0201_problems('<project xmlns="http://www.plcopen.org/xml/tc6_0201"><types>'
                             '<pous><pou><body><SFC><step localId="1" name="A"><connectionPointIn>'
                             '<connection refLocalId="7"/></connectionPointIn><position/></step>'
                             '</SFC></body></pou></pous></types></project>') == [
        "<step> children ['{http://www.plcopen.org/xml/tc6_0201}connectionPointIn', "
        "'{http://www.plcopen.org/xml/tc6_0201}position']",
        "connection to 7: no such object"]  # the check itself can fail


def test_an_edited_chart_is_never_exported_as_the_chart(tmp_path: Path) -> None:
    chart = tmp_path / "counter.xml"
    shutil.copy(ROOT / "tests/sfc/examples/beremiz_counter.xml", chart)
    net = compile_file(chart)
    chart.write_text(chart.read_text(encoding="utf-8").replace(
        "NOT Reset AND i1", "i1"), encoding="utf-8")
    with pytest.raises(ProgramError) as exc:
        export_plcopen(net, compile_file)
    first, *rest = exc.value.problems
    assert (first.file, first.line) == (str(chart), 1)
    assert "compiles to another net than the one exported" in first.message
    assert any("a chart keeps actions on steps" in p.message for p in rest)  # inferred: refused
    elsewhere = tmp_path / "other.xml"  # another chart, its POU named as this one's
    elsewhere.write_text(chart_xml(replace(QUALIFIERS, pou="CounterSFC")), encoding="utf-8")
    other = replace(compile_file(elsewhere), source=str(chart))
    with pytest.raises(ProgramError, match="compiles to another net"):
        export_plcopen(other, compile_file)


def test_a_chart_with_macro_steps_is_refused_at_the_macro_step(tmp_path: Path) -> None:
    path = ROOT / "tests/sfc/macro/mixer_macro.xml"
    with pytest.raises(ProgramError) as exc:
        export_plcopen(compile_file(path), compile_file)  # not inferred: flattened names
    [problem] = exc.value.problems
    line = next(n.line for n in parse_xml(path.read_bytes(), str(path)).walk()
                if n.tag == "macroStep")
    assert (problem.file, problem.line) == (str(path), line)
    assert "a chart with macro steps is not written back" in problem.message


def _unlined(items: list[Any]) -> list[Any]:
    return [replace(i, line=0) for i in items]


def test_the_chart_reads_back_the_same_steps_transitions_actions_and_interface(
        chart: Path) -> None:
    """In the chart's own terms (the reader's model), with an FB instance declared as well."""
    data = chart.read_bytes().replace(b"</localVars>", b'<variable name="t9"><type><derived '
                                      b'name="TON"/></type></variable></localVars>', 1)
    first = read_chart(data, str(chart))
    second = read_chart(write_chart(first, data).encode(), "back.xml")
    assert _unlined(second.steps) == _unlined(first.steps)
    assert [replace(t, condition=t.condition.strip()) for t in _unlined(second.transitions)] \
        == [replace(t, condition=t.condition.strip()) for t in _unlined(first.transitions)]
    def actions(c: Chart) -> list[Any]:  # an inline body is named after its XML line
        return [replace(a, name=re.sub(r"_inline\d+$", "_inline", a.name))
                for a in _unlined(c.actions)]
    assert actions(second) == actions(first)
    assert {k: replace(v, line=0) for k, v in second.variables.items()} == \
        {k: replace(v, line=0) for k, v in first.variables.items()}
    assert first.variables["T9"].iec == "TON"
