"""check/analyze on a chart report the SFC errors in the chart's terms: step and transition
names, XML lines, a witness path; every command refuses such a chart (the download gate
included: the program does not compile). A final step is a note, and the net gate's dead
marking, as for any net."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from softplc.analysis.gate import verify
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.sfc.load import load_chart
from tests.sfc.chartxml import ChartSpec, chart_xml
from tests.sfc.compare import compare

IO = {"go": ("BOOL", "%IX0.0"), "x": ("BOOL", "%IX0.1"), "y": ("BOOL", "%IX0.2"),
      "lamp": ("BOOL", "%QX0.0")}


def write(tmp_path: Path, spec: ChartSpec, name: str = "chart.xml") -> Path:
    path = tmp_path / name
    path.write_text(chart_xml(spec), encoding="utf-8")
    return path


def problems(path: Path) -> list[str]:
    with pytest.raises(ProgramError) as info:
        compile_file(path)
    return [str(p) for p in info.value.problems]


def line_of(path: Path, text: str) -> int:
    return next(i for i, line in enumerate(path.read_text().splitlines(), 1) if text in line)


def test_a_jump_out_of_a_parallel_branch_is_an_unsafe_chart_naming_the_step(
        tmp_path: Path) -> None:
    spec = ChartSpec(["Start", "Left", "Right", "Joined"], ["Start"], [
        (["Start"], ["Left", "Right"], "go"),
        (["Left"], ["Start"], "x"),          # leaves the parallel branch: the standard's error
        (["Left", "Right"], ["Joined"], "y"),
        (["Joined"], ["Start"], "TRUE")], variables=IO)
    path = write(tmp_path, spec)
    found = problems(path)
    assert len(found) == 1
    step_line = line_of(path, 'name="Right"')
    assert found[0].startswith(f"{path}:{step_line}: unsafe chart: step Right is activated "
                               "while it is active (two tokens)")
    assert "witness: Start_to_Left_Right -> Left_to_Start -> Start_to_Left_Right" in found[0]


def test_a_deadlock_outside_final_steps_is_refused_with_its_witness(tmp_path: Path) -> None:
    spec = ChartSpec(["Start", "A", "B", "A2", "B2"], ["Start"], [
        (["Start"], ["A", "B"], "go"), (["A"], ["A2"], "x"), (["B"], ["B2"], "y"),
        (["A2", "B"], ["Start"], "go")],  # the join waits for B, which may have gone on
        actions=[("A", "N", "lamp")], variables=IO)
    path = write(tmp_path, spec)
    (found,) = problems(path)
    a2 = line_of(path, 'name="A2"')
    assert found == (f"{path}:{a2}: deadlock: once A2, B2 are active "
                     "no transition can clear; witness: Start_to_A_B -> A_to_A2 -> B_to_B2")


def test_a_final_step_is_a_note_not_a_deadlock_and_the_gate_reports_its_marking(
        tmp_path: Path) -> None:
    spec = ChartSpec(["Start", "Fill", "Done"], ["Start"], [
        (["Start"], ["Fill"], "go"), (["Fill"], ["Done"], "x")],
        actions=[("Fill", "N", "lamp")], variables=IO)
    path = write(tmp_path, spec)
    done = line_of(path, 'name="Done"')
    chart = load_chart(path)
    assert [str(n) for n in chart.notes] == [
        f"{path}:{done}: final step Done: the chart ends there; witness: Start_to_Fill -> "
        "Fill_to_Done"]
    assert "Done: {}  # step Done (final: the chart ends there)" in chart.program_text
    verdict = verify(compile_file(path))  # the gate: as for any net's dead marking
    assert verdict.findings == (f"{path}:{done}: deadlock: marking {{Done: 1}} reached by "
                                "Start_to_Fill ; Fill_to_Done; no transition can ever fire "
                                "there",)
    assert compare(path, [{"go": k == 1, "x": k == 3} for k in range(8)]) is None


def test_unreachable_steps_and_transitions_that_never_clear_are_named(tmp_path: Path) -> None:
    spec = ChartSpec(["Start", "Run", "Orphan", "After"], ["Start"], [
        (["Start"], ["Run"], "go"), (["Run"], ["Start"], "NOT go"),
        (["Run", "Orphan"], ["After"], "x"),  # waits for a step nothing activates
        (["After"], ["Start"], "FALSE")], variables=IO)
    path = write(tmp_path, spec)
    found = problems(path)
    orphan = line_of(path, 'name="Orphan"')
    assert f"{path}:{orphan}: unreachable step Orphan: no sequence " \
        "of transitions from the initial steps activates it" in found
    assert any("unreachable step After" in p for p in found)
    assert any("transition Run_Orphan_to_After can never clear: its preceding steps Run, "
               "Orphan are never active together" in p for p in found)
    assert any("transition After_to_Start can never clear: its condition is FALSE" in p
               for p in found)


def test_check_on_the_command_line_reports_the_chart_and_fails(tmp_path: Path) -> None:
    spec = ChartSpec(["Start", "Wait", "Late"], ["Start"], [
        (["Start"], ["Wait"], "go"), (["Wait", "Late"], ["Start"], "x")], variables=IO)
    path = write(tmp_path, spec)
    run = subprocess.run([sys.executable, "-m", "softplc.cli", "check", str(path)],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 1
    assert "deadlock: once Wait is active" in run.stderr


def test_a_sound_chart_compiles_with_places_and_transitions_at_their_xml_lines(
        tmp_path: Path) -> None:
    spec = ChartSpec(["Start", "Run"], ["Start"], [(["Start"], ["Run"], "go"),
                                                   (["Run"], ["Start"], "NOT go")],
                     actions=[("Run", "N", "lamp")], variables=IO)
    path = write(tmp_path, spec)
    net = compile_file(path)
    assert net.place_names == ("Start", "Run")
    assert net.place_where[1] == (str(path), line_of(path, 'name="Run"'))
    assert net.transition_where[0][1] == line_of(path, "<![CDATA[go]]>")


def test_sd_with_its_r_step_active_at_the_same_time_is_refused_with_a_witness(
        tmp_path: Path) -> None:
    spec = ChartSpec(["S0", "A", "B"], ["S0"],
                     [(["S0"], ["A", "B"], "go"), (["A", "B"], ["S0"], "TRUE")],
                     [("A", "SD@T#1s", "q"), ("B", "R", "q")],
                     {"go": ("BOOL", "%IX0.0"), "q": ("BOOL", "%QX0.0")})
    path = tmp_path / "par.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    with pytest.raises(ProgramError) as info:
        compile_file(path)
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1)
                if 'qualifier="SD"' in t)
    assert [str(p) for p in info.value.problems] == [
        f"{path}:{line}: action q (SD) of step A: steps A and B (R q, line {line + 1}) can be "
        "active together, where IEC holds the latch reset while the R step is active (softplc "
        "resets it on entering the R step); witness: S0_to_A_B"]
