"""Token value types and resource limits at compile time (issue 19 parts 3 and 4): `softplc
check` refuses a date, NaN or an infinity, a list, null, a nested mapping, oversize text or integers
in `tokens:` at the line of the value, an arc weight over the limit at the arc's line, an
initial marking over a limit, and a bad `limits:` section; a valid `limits:` reaches the net.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.cli import main
from softplc.core.limits import DEFAULT, HARD
from softplc.core.problems import ProgramError
from softplc.core.values import MAX_TEXT
from tests.core.helpers import compile_program, write_io


def problems_of(tmp_path: Path, body: str) -> list[str]:
    with pytest.raises(ProgramError) as err:
        compile_program(tmp_path, body)
    return [str(p) for p in err.value.problems]


def one_token(tmp_path: Path, field_text: str) -> list[str]:
    # line 3: places:, line 4: the place, line 5: the token's field
    return problems_of(tmp_path, f"places:\n  parts:\n    tokens:\n      - {{{field_text}}}\n")


@pytest.mark.parametrize(("field_text", "expected"), [
    ("d: 2024-01-01", "field d: the date 2024-01-01 is not a token value"),
    ("kg: .nan", "field kg: nan is not a finite number"),
    ("kg: -.inf", "field kg: -inf is not a finite number"),
    ("l: [1, 2]", "field l: a list is not a token value"),
    ("n: null", "field n: null (an empty value) is not a token value"),
    ("n: ~", "field n: null (an empty value) is not a token value"),
    ("m: {a: 1}", "field m: a nested mapping is not a token value"),
    ("big: 9223372036854775808", "field big: integer 9223372036854775808 is out of range"),
    (f"s: {'x' * (MAX_TEXT + 1)}", f"field s: text of {MAX_TEXT + 1} characters (at most"),
    ("_hidden: 1", "field name '_hidden' starts with _"),
    ("1: 2", "field name 1 is not a name"),
])
def test_check_refuses_a_token_value_the_runtime_cannot_carry_at_its_line(
        tmp_path: Path, field_text: str, expected: str) -> None:
    found = one_token(tmp_path, field_text)
    assert len(found) == 1, found
    assert found[0].startswith(f"{tmp_path / 'prog.yaml'}:6: places.parts.tokens[0]"), found
    assert expected in found[0]


def test_each_bad_field_of_several_records_is_located(tmp_path: Path) -> None:
    body = ("places:\n  parts:\n    tokens:\n      - {id: 1, kg: 5}\n      - {id: 2, kg: .nan}\n"
            "      - {id: 3, when: 2024-01-01}\n      - 7\n")
    found = problems_of(tmp_path, body)
    f = tmp_path / "prog.yaml"
    assert [s.split(": ", 2)[0] + ": " + s.split(": ", 2)[1] for s in found] == [
        f"{f}:7: places.parts.tokens[1].kg", f"{f}:8: places.parts.tokens[2].when",
        f"{f}:9: places.parts.tokens[3]"]
    assert "a value of type int is not a token record" in found[2]


def test_valid_values_compile_unchanged(tmp_path: Path) -> None:
    net = compile_program(tmp_path, (
        "places:\n  parts: {tokens: [{id: 1, ok: true, tag: 'A-1', neg: -9223372036854775807, "
        f"s: '{'x' * MAX_TEXT}'}}]}}\n"))
    (token,) = net.initial_tokens[0]
    assert token == {"id": 1, "ok": True, "tag": "A-1", "neg": -(2**63 - 1), "s": "x" * MAX_TEXT}
    assert type(token["ok"]) is bool and net.limits == DEFAULT


def test_a_long_text_constant_in_an_expression_is_refused(tmp_path: Path) -> None:
    long = "y" * (MAX_TEXT + 1)
    found = problems_of(tmp_path, (
        "places:\n  a: {tokens: [{id: 1}]}\n  b: {coloured: true}\ntransitions:\n"
        "  t: {from: [{place: a, var: p}], "
        f"to: [{{place: b, token: {{tag: \"'{long}'\"}}}}]}}\n"))
    assert len(found) == 1 and f"text of {MAX_TEXT + 1} characters" in found[0]
    assert found[0].startswith(f"{tmp_path / 'prog.yaml'}:7:")


def test_check_refuses_a_weight_over_the_limit_at_the_arcs_line(tmp_path: Path) -> None:
    found = problems_of(tmp_path, (
        "places:\n  p: {tokens: 1}\n  q: {}\ntransitions:\n  t:\n    from: [p]\n"
        "    to: [{place: q, weight: 100000000}]\n"))
    assert found == [f"{tmp_path / 'prog.yaml'}:9: transitions.t.to: arc weight 100,000,000 "
                     f"of 'q' exceeds the limit {DEFAULT.weight:,} (limits.weight)"]


def test_repeated_arcs_add_up_against_the_weight_limit(tmp_path: Path) -> None:
    found = problems_of(tmp_path, (
        "limits: {weight: 3}\nplaces:\n  p: {tokens: 1}\n  q: {}\ntransitions:\n"
        "  t: {from: [p], to: [q, q, {q: 2}]}\n"))
    assert len(found) == 1 and "arc weight 4 of 'q' exceeds the limit 3" in found[0]


def test_a_coloured_arc_cannot_build_more_records_than_a_place_holds(tmp_path: Path) -> None:
    found = problems_of(tmp_path, (
        "places:\n  p: {tokens: 1}\n  c: {coloured: true}\ntransitions:\n"
        "  t: {from: [p], to: [{place: c, weight: 20000, token: {n: '1'}}]}\n"))
    assert len(found) == 1 and "to coloured place 'c' exceeds the limit 10,000" in found[0]


def test_an_initial_marking_over_a_limit_is_refused(tmp_path: Path) -> None:
    found = problems_of(tmp_path, (
        "limits:\n  place_tokens: 10\n  coloured_total: 2\nplaces:\n  p: {tokens: 11}\n"
        "  c: {tokens: [{a: 1}, {a: 2}, {a: 3}]}\n"))
    assert any(":7: places.p: initial tokens (11) exceed the limit 10 (limits.place_tokens)"
               in s for s in found), found
    assert any("initial coloured tokens (3) exceed the limit 2" in s for s in found), found


@pytest.mark.parametrize(("line", "expected"), [
    ("weight: 2000000", f"limit weight must be a whole number from 1 to {HARD.weight:,}"),
    ("coloured_place: 0", "limit coloured_place must be a whole number from 1"),
    ("tokens: 5", "unknown limit 'tokens'; expected one of weight, place_tokens"),
    ("bindings_per_scan: lots", "limit bindings_per_scan must be a whole number"),
])
def test_a_bad_limits_section_is_located(tmp_path: Path, line: str, expected: str) -> None:
    found = problems_of(tmp_path, f"limits:\n  {line}\nplaces:\n  p: {{tokens: 1}}\n")
    assert len(found) == 1 and found[0].startswith(f"{tmp_path / 'prog.yaml'}:4: limits.")
    assert expected in found[0]


def test_limits_of_a_program_reach_the_compiled_net(tmp_path: Path) -> None:
    net = compile_program(tmp_path, (
        "limits: {coloured_place: 50, bindings_per_scan: 200000}\nplaces:\n  p: {tokens: 1}\n"))
    assert net.limits.coloured_place == 50 and net.limits.bindings_per_scan == 200_000
    assert net.limits.weight == DEFAULT.weight


def test_softplc_check_prints_the_located_problem_and_fails(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_io(tmp_path)
    prog = tmp_path / "dated.yaml"
    prog.write_text("program: dated\nio_image: io.yaml\n"
                    "places:\n  p: {tokens: [{d: 2024-01-01}]}\n", encoding="utf-8")
    assert main(["check", str(prog)]) == 1
    err = capsys.readouterr()
    text = err.out + err.err
    assert f"{prog}:4: places.p.tokens[0].d: field d: the date 2024-01-01 is not a token value" \
        in text
