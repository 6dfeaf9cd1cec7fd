"""Reading PLCopen XML: the ST subset's translation, located refusals of what is outside it,
POU choice, hostile XML, and `softplc import` writing a program that compiles to the same net."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.sfc.st import StError, emit, parse_condition, parse_statements
from tests.sfc.chartxml import ChartSpec, chart_xml

EXAMPLES = Path(__file__).parent / "examples"
NAMES = {"A": ("a", "bool"), "B": ("b", "bool"), "CNT": ("Cnt", "int"),
         "T1": ("T1", "time"), "LEVEL": ("level", "real")}


@pytest.mark.parametrize(("st", "py"), [
    ("NOT a = b", "((not a) == b)"),             # NOT binds tighter than = in ST
    ("a AND b OR NOT a", "((a and b) or (not a))"),
    ("a XOR b", "(a != b)"),
    ("a & b", "(a and b)"),
    ("Cnt > 3 AND T1 > T#7S or T1 > T#1H1M", "(((Cnt > 3) and (T1 > 7000)) or (T1 > 3660000))"),
    (":= AND(a, b, a);", "(a and b and a)"),
    ("Cnt / 2 + 1 >= 4", "((trunc(Cnt / 2) + 1) >= 4)"),  # integer / truncates in ST
    ("1 < Cnt = TRUE", "((1 < Cnt) == true)"),          # no Python chained comparison
    ("a = 1", "(a == 1)"),
    ("SEL(a, Cnt, 16#10)", "(16 if a else Cnt)"),
    ("level * 2.5 <= 1.0E2", "((level * 2.5) <= 100.0)"),
])
def test_st_conditions_translate_with_st_precedence(st: str, py: str) -> None:
    assert emit(parse_condition(st, NAMES, {}))[0] == py


@pytest.mark.parametrize(("st", "why"), [
    ("Cnt MOD 2 = 0", "MOD truncates toward zero"),
    ("Cnt AND 1", "AND/OR/NOT of integers are bitwise"),
    ("TON1.Q", "only the step flags"),
    ("foo", "unknown variable 'foo'"),
    ("T#1.5ms > T1", "finer than a millisecond"),
    ("a AND (b", "expected ')'"),
    ("R_TRIG(a)", "function R_TRIG() is not supported"),
])
def test_st_outside_the_subset_is_refused_with_the_construct(st: str, why: str) -> None:
    with pytest.raises(StError) as info:
        emit(parse_condition(st, NAMES, {}))
    assert why in info.value.message


def test_statements_are_assignments_only() -> None:
    got = [(v, emit(e)[0]) for v, _, e, _ in parse_statements("Cnt := Cnt + 1; a:=FALSE;",
                                                              NAMES, {})]
    assert got == [("Cnt", "(Cnt + 1)"), ("a", "false")]
    with pytest.raises(StError, match="no IF, CASE"):
        parse_statements("IF a THEN Cnt := 1; END_IF;", NAMES, {})


def _chart(tmp_path: Path, **changes: object) -> Path:
    spec = ChartSpec(["Start", "Run"], ["Start"], [(["Start"], ["Run"], "go"),
                                                   (["Run"], ["Start"], "NOT go")],
                     variables={"go": ("BOOL", "%IX0.0"), "lamp": ("BOOL", "%QX0.0"),
                                "n": ("INT", "")})
    for key, value in changes.items():
        setattr(spec, key, value)
    path = tmp_path / "chart.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    return path


def _problems(path: Path | str) -> list[str]:
    with pytest.raises(ProgramError) as info:
        compile_file(path)
    return [str(p) for p in info.value.problems]


def test_refusals_are_located_at_the_xml_line_with_what_is_supported(tmp_path: Path) -> None:
    path = _chart(tmp_path, actions=[("Run", "DL@T#2s", "lamp"), ("Run", "S", "bump")],
                  transitions=[(["Start"], ["Run"], "go AND n MOD 2 = 0"),
                               (["Run"], ["Start"], "NOT go")], bodies={"bump": "n := 1;"})
    lines = path.read_text().splitlines()
    found = _problems(path)
    cond = next(i for i, t in enumerate(lines, 1) if "MOD" in t)
    timed = next(i for i, t in enumerate(lines, 1) if 'qualifier="DL"' in t)
    stored = next(i for i, t in enumerate(lines, 1) if 'qualifier="S"' in t)
    assert found == sorted([
        f"{path}:{cond}: transition Start_to_Run: MOD truncates toward zero in ST and floors "
        "in softplc; not translated",
        f"{path}:{timed}: action lamp of step Run: qualifier DL T#2s is in the PLCopen schema "
        "only: IEC 61131-3 defines no ACTION_CONTROL rule for it, so there is nothing to map "
        "(supported: N, S, R, P, P1, P0, and L, D, DS, SD, SL with a duration, on BOOL "
        "variables; N, P1, P0 on ST bodies)",
        f"{path}:{stored}: action bump of step Run: S with an ST body is stored: it would run "
        "every scan until reset; supported: N, P1, P0 bodies, or a BOOL variable as the action",
    ])


def test_timed_actions_are_refused_where_their_timer_would_be_wrong(tmp_path: Path) -> None:
    path = _chart(tmp_path, actions=[("Run", "D", "lamp"), ("Start", "L@T#1s", "go"),
                                     ("Run", "DS@T#1x", "n"), ("Run", "L@2s", "lamp")])
    lines = path.read_text().splitlines()
    at = {q: next(i for i, t in enumerate(lines, 1) if f'qualifier="{q}"' in t)
          for q in ("D", "L")}
    found = _problems(path)
    assert f"{path}:{at['D']}: action lamp of step Run: qualifier D needs a positive duration " \
        "(duration=\"T#2s\"), got ''" in found
    assert f"{path}:{at['D'] + 2}: action n of step Run: DS T#1x is supported on a BOOL " \
        "variable only (an ST body would need a per-scan timer)" in found
    path = _chart(tmp_path, actions=[("Start", "L@T#1s", "lamp"), ("Run", "N", "lamp")])
    line = next(i for i, t in enumerate(path.read_text().splitlines(), 1) if "T#1s" in t)
    assert _problems(path) == [
        f"{path}:{line}: action lamp (L T#1s) of step Start: lamp is also driven by N in step "
        f"Run (line {line + 1}); a timed action must be the only one driving its BOOL (R of a "
        "DS excepted)",
        f"{path}:{line}: action lamp (L T#1s) of step Start: on the initial step no transition "
        "starts its timer; move it to a later step"]


def test_a_file_with_several_charts_needs_the_pou_named(tmp_path: Path) -> None:
    one = _chart(tmp_path).read_text()
    pou = one[one.index("<pou "):one.index("</pou>") + 6]
    two = one.replace("</pous>", pou.replace('name="Chart"', 'name="Other"') + "</pous>")
    path = tmp_path / "two.xml"
    path.write_text(two, encoding="utf-8")
    (found,) = _problems(path)
    assert "several SFC POUs (Chart, Other): name one with --pou POU or FILE.xml#POU" in found
    assert compile_file(f"{path}#Other").name == "Other"
    assert "no SFC POU named 'Nope'; SFC POUs in the file: Chart, Other" in \
        _problems(f"{path}#Nope")[0]


def test_entities_are_refused_and_change_nothing(tmp_path: Path) -> None:
    path = tmp_path / "bomb.xml"
    path.write_text('<?xml version="1.0"?><!DOCTYPE p [<!ENTITY a "aaaa">]>'
                    '<project xmlns="http://www.plcopen.org/xml/tc6_0201">&a;</project>')
    (found,) = _problems(path)
    assert found.startswith(f"{path}:1: refused XML")


def test_unlocated_variables_become_memory_with_their_iec_types(tmp_path: Path) -> None:
    net = compile_file(_chart(tmp_path))
    n = net.io.symbols["n"]
    assert (str(n.address), n.type.value) == ("%MW0", "int")
    assert str(net.io.symbols["go"].address) == "%IX0.0"


def test_import_writes_a_program_that_compiles_to_the_same_net(tmp_path: Path) -> None:
    chart = EXAMPLES / "codesys_press.xml"
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "softplc.cli", "import", str(chart), "-o",
                          str(out)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    text = (out / "Press.yaml").read_text()
    assert f"Pressing: {{outputs: [down]}}  # step Pressing, {chart}:" in text
    assert "delay: 50ms" in text
    imported, direct = compile_file(out / "Press.yaml"), compile_file(chart)
    assert imported.place_names == direct.place_names
    assert [replace(t, line=0) for t in imported.transitions] == \
        [replace(t, line=0) for t in direct.transitions]  # arcs, guards, delays, actions
    assert sorted(imported.io.symbols) == sorted(direct.io.symbols)
