"""`softplc export --format plcopen`: a net that is a chart is written as PLCopen XML that
reads back to the same net; a net that is not is refused with a located reason per place or
transition."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

from softplc.program.compiler import compile_file
from softplc.sfc.export import export_plcopen
from softplc.sfc.reader import read_chart
from tests.sfc.chartxml import ChartSpec, chart_xml

ROOT = Path(__file__).parents[2]


def export(program: Path | str, out: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", "export", str(program),
                           "--format", "plcopen", "-o", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=60)


def test_a_chart_goes_out_and_back_to_the_same_net(tmp_path: Path) -> None:
    spec = ChartSpec(["Idle", "A", "B", "C", "D"], ["Idle"], [
        (["Idle"], ["A", "B"], "go AND NOT stop"), (["A"], ["C"], "x"),
        (["A"], ["C"], "y AND B.X"), (["B", "C"], ["D"], "TRUE"),
        (["D"], ["Idle"], "D.T >= T#50ms")], [("A", "N", "lamp"), ("D", "N", "lamp")],
        {"go": ("BOOL", "%IX0.0"), "stop": ("BOOL", "%IX0.1"), "x": ("BOOL", "%IX0.2"),
         "y": ("BOOL", "%IX0.3"), "lamp": ("BOOL", "%QX0.0"), "n": ("INT", "%MW3")})
    chart = tmp_path / "chart.xml"
    chart.write_text(chart_xml(spec), encoding="utf-8")
    back = tmp_path / "back.xml"
    done = export(chart, back)
    assert done.returncode == 0, done.stderr
    first, second = compile_file(chart), compile_file(back)
    assert first.place_names == second.place_names
    assert [replace(t, line=0) for t in first.transitions] == \
        [replace(t, line=0) for t in second.transitions]
    assert first.order == second.order and first.place_outputs == second.place_outputs
    assert {n: str(s.address) for n, s in first.io.symbols.items()} == \
        {n: str(s.address) for n, s in second.io.symbols.items()}


def test_a_net_that_is_not_a_chart_is_refused_with_the_reasons(tmp_path: Path) -> None:
    done = export("programs/drilling.yaml", tmp_path / "d.xml")
    assert done.returncode == 1
    assert not (tmp_path / "d.xml").exists()
    lines = done.stderr.splitlines()
    assert "programs/drilling.yaml:19: not an SFC: place counter holds coloured tokens (a step " \
        "holds no data)" in lines
    assert "programs/drilling.yaml:34: not an SFC: transition drill has a duration (an SFC " \
        "transition clears at once)" in lines


def test_the_drawing_is_kept_each_step_and_transition_where_it_was(tmp_path: Path) -> None:
    spec = ChartSpec(["Idle", "A", "B", "C"], ["Idle"], [
        (["Idle"], ["A", "B"], "go"), (["A"], ["C"], "x"), (["A"], ["C"], "y"),
        (["B", "C"], ["Idle"], "TRUE")], [("A", "N", "lamp")],
        {"go": ("BOOL", "%IX0.0"), "x": ("BOOL", "%IX0.1"), "y": ("BOOL", "%IX0.2"),
         "lamp": ("BOOL", "%QX0.0")})
    drawn = iter(range(1, 1000))

    def place(m: re.Match[str]) -> str:  # as an editor draws: every object somewhere else
        k = next(drawn)
        return f'{m.group(1)}<position x="{37 * k}" y="{120 + 53 * k}"/>'

    text = re.sub(r'(<step [^>]*>)', place, chart_xml(spec))
    text = re.sub(r'(<transition [^>]*>)<position [^>]*/>', place, text)
    chart = tmp_path / "chart.xml"
    chart.write_text(text, encoding="utf-8")
    back = tmp_path / "back.xml"
    done = export(chart, back)
    assert done.returncode == 0, done.stderr

    def drawing(path: Path) -> dict[str, tuple[float, float] | None]:
        c = read_chart(path.read_bytes(), str(path))
        return {s.name: (s.x, s.y) for s in c.steps} | {t.name: t.xy for t in c.transitions}

    first = drawing(chart)
    assert len(set(first.values())) == 8 and None not in first.values()
    assert drawing(back) == first


def test_a_chart_with_stored_actions_and_st_bodies_is_written_back(tmp_path: Path) -> None:
    """programs/drilling_sfc.xml (S, R, P1 on a POU action's ST body: transition `do:`s and
    set/reset places in the net) was refused before; now the chart itself goes back out."""
    back = tmp_path / "drilling_sfc.xml"
    done = export(ROOT / "programs/drilling_sfc.xml", back)
    assert done.returncode == 0, done.stderr
    c = read_chart(back.read_bytes(), str(back))
    assert [(a.step, a.qualifier, a.name) for a in c.actions] == \
        [(a.step, a.qualifier, a.name) for a in read_chart(
            (ROOT / "programs/drilling_sfc.xml").read_bytes(), "drilling_sfc.xml").actions]
    text = back.read_text(encoding="utf-8")
    assert "<![CDATA[parts_drilled := parts_drilled + 1;]]>" in text
    assert "<documentation><xhtml:p><![CDATA[parts drilled since start]]></xhtml:p>" in text


def test_the_named_pou_of_a_file_with_several_is_written_back(tmp_path: Path) -> None:
    def one(pou: str, qualifier: str) -> str:
        return chart_xml(ChartSpec(["S0", "S1"], ["S0"], [(["S0"], ["S1"], "i"),
                                                           (["S1"], ["S0"], "NOT i")],
                                   [("S1", qualifier, "o")],
                                   {"i": ("BOOL", "%IX0.0"), "o": ("BOOL", "%QX0.0")}, pou=pou))
    second = re.search(r"<pou .*</pou>", one("Second", "N"), re.S)
    assert second is not None
    path = tmp_path / "two.xml"
    path.write_text(one("First", "S").replace("</pous>", second.group(0) + "</pous>"),
                    encoding="utf-8")
    text = export_plcopen(compile_file(f"{path}#First"), compile_file)
    assert '<pou name="First"' in text and "Second" not in text
    assert '<action localId="0" qualifier="S"><reference name="o"/></action>' in text


def test_without_the_compiler_a_chart_net_is_inferred_as_before(tmp_path: Path) -> None:
    """The inference path (every net not compiled from a chart, YAML ones included) still
    writes a net that is a chart and reads back to the same net."""
    spec = ChartSpec(["Idle", "A"], ["Idle"], [(["Idle"], ["A"], "go"), (["A"], ["Idle"], "x")],
                     [("A", "N", "lamp")], {"go": ("BOOL", "%IX0.0"), "x": ("BOOL", "%IX0.1"),
                                            "lamp": ("BOOL", "%QX0.0")})
    chart = tmp_path / "chart.xml"
    chart.write_text(chart_xml(spec), encoding="utf-8")
    first = compile_file(chart)
    back = tmp_path / "back.xml"
    back.write_text(export_plcopen(first), encoding="utf-8")
    assert 'height="30" width="90"' in back.read_text(encoding="utf-8")  # inferred: one column
    second = compile_file(back)
    assert [replace(t, line=0) for t in first.transitions] == \
        [replace(t, line=0) for t in second.transitions]


def test_the_command_counts_the_chart_s_steps_not_the_net_s_places(tmp_path: Path) -> None:
    spec = ChartSpec(["S0", "S1"], ["S0"], [(["S0"], ["S1"], "i"), (["S1"], ["S0"], "NOT i")],
                     [("S1", "S", "o"), ("S0", "R", "o"), ("S1", "L@T#20ms", "p")],
                     {"i": ("BOOL", "%IX0.0"), "o": ("BOOL", "%QX0.0"), "p": ("BOOL", "%QX0.1")})
    chart = tmp_path / "chart.xml"
    chart.write_text(chart_xml(spec), encoding="utf-8")
    assert len(compile_file(chart).place_names) > 2  # set/reset memory, the L timer
    done = export(chart, tmp_path / "back.xml")
    assert done.returncode == 0, done.stderr
    assert done.stdout.endswith("back.xml: an SFC of 2 steps\n")
