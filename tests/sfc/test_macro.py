"""Macro steps (PLCopen `<macroStep><body><SFC>`): expanded inline between the body's entry and
exit steps, inner names `MACRO.Inner`, problems at the inner XML lines; the expanded chart runs
scan by scan as the same chart written flat by hand (tests/sfc/macro/)."""

from __future__ import annotations

import random
import re
from pathlib import Path

import pytest

from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.sfc.load import load_chart
from tests.core.helpers import Bench
from tests.fuzz.budget import scaled

HERE = Path(__file__).parent / "macro"
MACRO, FLAT = HERE / "mixer_macro.xml", HERE / "mixer_flat.xml"
OUTPUTS = ("Valve", "Stir", "Batches")


def _inputs(seed: int, scans: int) -> list[dict[str, int]]:
    """Held inputs with changes now and then: long enough holds for the 500 ms step timer."""
    rng, out, start, level = random.Random(seed), [], 0, 0
    for _ in range(scans):
        if rng.random() < 0.02:
            start = 1 - start
        if rng.random() < 0.02:
            level = rng.choice((0, 30, 49, 50, 79, 80, 100))
        out.append({"Start": start, "Level": level})
    return out


def _run(path: Path, inputs: list[dict[str, int]]) -> list[tuple[object, ...]]:
    bench, trace = Bench(compile_file(path)), []
    for k, values in enumerate(inputs, start=1):
        bench.set(**values)
        bench.scan(k * 10_000_000)
        steps = sorted(p.replace("Fill.Last.", "Fill_").replace("Fill.", "Fill_")
                       for p, n in bench.marking().items() if n)
        trace.append((tuple(steps), *(bench.get(o) for o in OUTPUTS)))
    return trace


@pytest.mark.parametrize("seed", range(scaled(4)))
def test_the_expanded_macro_runs_as_the_chart_written_flat(seed: int) -> None:
    inputs = _inputs(seed, 600)
    macro, flat = _run(MACRO, inputs), _run(FLAT, inputs)
    assert macro == flat
    visited = {s for steps, *_ in macro for s in steps}
    assert visited == {"Idle", "Fill_Open", "Fill_Settle", "Fill_Done"}  # the run went through


NESTED = (  # mixer_macro.xml's step Done and its action block inside a macro step Last
    '<macroStep localId="11" name="Last"><position x="300" y="260"/><connectionPointIn>'
    '<connection refLocalId="9"/></connectionPointIn><connectionPointOut/><body><SFC>\n'
    '<step localId="1" name="Done" initialStep="true"><position x="0" y="0"/>'
    '<connectionPointOut formalParameter=""/></step>\n'
    '<actionBlock localId="2"><position x="0" y="0"/><connectionPointIn><connection '
    'refLocalId="1"/></connectionPointIn>\\1</actionBlock>\n</SFC></body></macroStep>')


def test_a_nested_macro_runs_as_the_chart_written_flat(tmp_path: Path) -> None:
    path = tmp_path / "nested.xml"
    path.write_text(re.sub(r'<step localId="11" name="Done">.*?<actionBlock localId="12">.*?'
                           r'(<action .*?</action>)\s*</actionBlock>', NESTED,
                           MACRO.read_text(encoding="utf-8"), count=1, flags=re.S))
    chart = load_chart(path).chart
    assert [s.name for s in chart.steps] == ["Idle", "Fill.Open", "Fill.Settle",
                                             "Fill.Last.Done"]
    assert next(a for a in chart.actions if a.qualifier == "P1").step == "Fill.Last.Done"
    inputs = _inputs(7, 600)
    assert _run(path, inputs) == _run(FLAT, inputs)


def test_inner_steps_are_prefixed_and_keep_their_xml_lines() -> None:
    chart = load_chart(MACRO).chart
    lines = MACRO.read_text(encoding="utf-8").splitlines()
    where = {s.name: s.line for s in chart.steps}
    assert list(where) == ["Idle", "Fill.Open", "Fill.Settle", "Fill.Done"]
    assert 'name="Settle"' in lines[where["Fill.Settle"] - 1]
    names = {t.name: t for t in chart.transitions}
    assert names["Fill.Settle_to_Fill.Done"].delay_ms == 500  # `Settle.T`: the macro's own name
    assert names["Fill.Settle_to_Fill.Open"].targets == ("Fill.Open",)  # the inner jump
    assert names["Idle_to_Fill.Open"].targets == ("Fill.Open",)  # into the entry step
    assert names["Fill.Done_to_Idle"].sources == ("Fill.Done",)  # out of the exit step
    assert {(a.step, a.qualifier) for a in chart.actions} == {
        ("Fill.Open", "N"), ("Fill.Settle", "N"), ("Fill.Done", "P1")}


def _variant(tmp_path: Path, *edits: tuple[str, str]) -> Path:
    text = MACRO.read_text(encoding="utf-8")
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = tmp_path / "variant.xml"
    path.write_text(text, encoding="utf-8")
    return path


def _line(path: Path, needle: str) -> int:
    return next(i for i, t in enumerate(path.read_text().splitlines(), 1) if needle in t)


def _problems(path: Path) -> list[str]:
    with pytest.raises(ProgramError) as info:
        compile_file(path)
    return [str(p) for p in info.value.problems]


def test_a_jump_to_the_macro_enters_its_entry_step(tmp_path: Path) -> None:
    path = _variant(tmp_path, ('<jumpStep localId="5" targetName="Idle">',
                               '<jumpStep localId="5" targetName="fill">'))
    chart = load_chart(path).chart
    back = next(t for t in chart.transitions if t.sources == ("Fill.Done",))
    assert back.targets == ("Fill.Open",)


def test_a_macro_without_entry_or_exit_is_a_located_refusal(tmp_path: Path) -> None:
    no_entry = _variant(tmp_path, ('name="Open" initialStep="true"', 'name="Open"'))
    at = _line(no_entry, "<macroStep localId")
    assert _problems(no_entry) == [  # only this: the macro's wires stay on a stand-in step
        f"{no_entry}:{at}: macro step Fill: its body needs exactly one initial step, the entry "
        "step the macro's preceding transitions enter; found none"]
    (tmp_path / "loop").mkdir()
    no_exit = _variant(tmp_path / "loop", (INNER_END, LOOP_BACK + INNER_END))
    assert _problems(no_exit) == [
        f"{no_exit}:{at}: macro step Fill: its body needs exactly one exit step (a step no "
        "transition of the body leaves), which the macro's following transitions leave; "
        "found none"]


INNER_END = "                </SFC>\n              </body>"
LOOP_BACK = (
    '<transition localId="13"><position x="0" y="0"/><connectionPointIn><connection '
    'refLocalId="11"/></connectionPointIn><condition><inline name=""><ST><xhtml:p>TRUE'
    '</xhtml:p></ST></inline></condition></transition><jumpStep localId="14" '
    'targetName="Open"><position x="0" y="0"/><connectionPointIn><connection refLocalId="13"/>'
    '</connectionPointIn></jumpStep>\n')


def test_a_macro_whose_body_is_not_an_sfc_is_refused(tmp_path: Path) -> None:
    text = MACRO.read_text(encoding="utf-8")
    path = tmp_path / "st.xml"
    path.write_text(re.sub(r"\n {14}<body>.*?\n {14}</body>", "\n<body><ST><xhtml:p>x := 1;"
                           "</xhtml:p></ST></body>", text, count=1, flags=re.S))
    assert _problems(path) == [
        f"{path}:{_line(path, '<macroStep localId')}: macro step Fill has an ST body: a macro "
        "step's body must be an SFC (<body><SFC>: its entry step, ..., its exit step)"]


def test_a_jump_out_of_a_macro_is_refused(tmp_path: Path) -> None:
    path = _variant(tmp_path, ('<jumpStep localId="8" targetName="Open">',
                               '<jumpStep localId="8" targetName="Idle">'))
    at = _line(path, 'targetName="Idle">')
    assert f"{path}:{at}: jump to 'Idle' in macro step Fill: " \
        "no step of that name in the macro (a jump does not leave a macro: its exit step " \
        "does)" in _problems(path)


def test_verification_names_the_inner_steps_at_their_lines(tmp_path: Path) -> None:
    path = _variant(tmp_path, ("Level >= 80", "FALSE"))
    found = _problems(path)
    open_, settle = _line(path, 'name="Open"'), _line(path, 'name="Settle"')
    cond = _line(path, '<transition localId="3">')
    assert f"{path}:{open_}: deadlock: once Fill.Open is active no transition can clear; " \
        "witness: Idle_to_Fill.Open" in found
    assert f"{path}:{cond}: transition Fill.Open_to_Fill.Settle can never clear: its " \
        "condition is FALSE" in found
    assert f"{path}:{settle}: unreachable step Fill.Settle: no sequence of transitions from " \
        "the initial steps activates it" in found


def test_an_action_block_on_the_macro_step_is_refused_alone(tmp_path: Path) -> None:
    block = ('<actionBlock localId="9"><position x="0" y="0"/><connectionPointIn><connection '
             'refLocalId="3"/></connectionPointIn><action localId="0"><reference name="Stir"/>'
             '</action></actionBlock>\n            ')
    path = _variant(tmp_path, ('<transition localId="4">', block + '<transition localId="4">'))
    at = _line(path, '<actionBlock localId="9">')
    assert _problems(path) == [f"{path}:{at}: an "
                               "action block on a macro step: attach the actions to the steps "
                               "in its body"]
