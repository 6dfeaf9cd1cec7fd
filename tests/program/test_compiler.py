"""Program validation: every bad program of the corpus under tests/program/bad/ with its exact
`FILE:LINE: path: message` lines, several problems reported at once, `softplc check`.

`{F}` in an expected line is the program file, `{BAD}` the corpus directory (absolute, as the
compiler resolves referenced files).
"""

from __future__ import annotations

import builtins
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from softplc.cli import main
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file, compile_text, summarize

HERE = Path(__file__).resolve().parent
BAD = HERE / "bad"
REPO = HERE.parent.parent
PROGRAMS = REPO / "programs"
TRAP = "is text here, not a boolean: write true or false"

CORPUS: dict[str, list[str]] = {
    "duplicate_key.yaml": [
        "{F}:4: idle: duplicate key 'idle' (first at line 3)",
    ],
    "trap_tokens_yes.yaml": [
        "{F}:3: places.idle.tokens: tokens must be a whole number >= 0 or a list of records "
        f"('yes' {TRAP})",
    ],
    "trap_when_on.yaml": [
        f"{{F}}:9: transitions.go.when: guard 'on' ('on' {TRAP})",  # and no second problem
    ],
    "trap_safe_off.yaml": [
        "{BAD}/io_safe_off.yaml:3: symbols.lamp.safe: safe value of a bool must be true or false "
        f"('off' {TRAP})",
    ],
    "unknown_place.yaml": [
        "{F}:7: transitions.go.to: arc to unknown place 'nowhere'",
    ],
    "weight_zero.yaml": [
        "{F}:7: transitions.go.from: arc weight of 'idle' must be a whole number >= 1",
    ],
    "unknown_symbol.yaml": [
        "{F}:10: transitions.go.do[0]: unknown symbol 'siren' (not in {BAD}/io.yaml)",
    ],
    "unknown_event.yaml": [
        "{F}:10: transitions.go.do[0]: event 'finished' is not declared in the program's events:",
    ],
    "write_input.yaml": [
        "{F}:10: transitions.go.do[0]: start is an input (%IX0.0); a program cannot write it",
    ],
    "set_word.yaml": [
        "{F}:10: transitions.go.do[0]: counter is a word; expected a bool here",
    ],
    "output_type.yaml": [
        "{F}:3: places.idle.outputs: lamp is a bool; its output value must be true or false",
        "{F}:4: places.busy.outputs: counter is a word; its output value must be 0..65535",
    ],
    "guard_escape.yaml": [
        "{F}:9: transitions.go.when: only these functions may be called: abs, dint, falling, int, "
        "lreal, max, min, real, rising, trunc, udint, word in "
        "\"__import__('os').system('touch pwned')\"",
    ],
    "subnet_missing_param.yaml": [
        "{BAD}/nets/blinker.yaml:12: transitions.switch_on.when: unknown name 'button': not a "
        "symbol, event or token variable in 'button'",
        "{F}:3: subnets.b1: subnet nets/blinker.yaml needs parameter 'button'",
    ],
    "subnet_extra_param.yaml": [
        "{F}:3: subnets.b1.with.colour: subnet nets/blinker.yaml has no parameter 'colour' "
        "(it takes: light, button)",
    ],
    "subnet_param_escape.yaml": [
        "{BAD}/nets/blinker.yaml:12: transitions.switch_on.when: only these functions may be "
        "called: abs, dint, falling, int, lreal, max, min, real, rising, trunc, udint, word in "
        "\"__import__('os').system('touch pwned')\"",
    ],
    "bad_duration.yaml": [
        "{F}:10: transitions.go.duration: bad duration '2 parsecs': expected a number with a unit "
        "(ns, us, ms, s, min, h), e.g. 10ms or 2s",
    ],
    "unknown_keys.yaml": [
        "{F}:3: places.idle.colour: unknown key 'colour' (did you mean 'coloured'?); expected "
        "one of capacity, coloured, description, outputs, retain, tokens",
        "{F}:9: transitions.go.guard: unknown key 'guard' (did you mean 'when'?); expected one "
        "of delay, description, do, duration, from, inhibit, outputs, priority, read, to, when",
    ],
    "misspelt_names.yaml": [
        "{F}:9: transitions.go.to: arc to unknown place 'bussy' (did you mean 'busy'?)",
        "{F}:10: transitions.go.when: unknown name 'strat': not a symbol, event or token "
        "variable in 'strat and not flgg' (did you mean 'start'?)",
        "{F}:11: transitions.go.do[0]: unknown symbol 'lmap' (not in {BAD}/io.yaml) "
        "(did you mean 'lamp'?)",
        "{F}:11: transitions.go.do[1]: event 'finishd' is not declared in the program's events: "
        "(did you mean 'finished'?)",
    ],
    "missing_io_image.yaml": [
        "{F}:1: io_image: missing io_image: (the symbols file)",
    ],
    "several_problems.yaml": [
        "{F}:8: transitions.go.to: arc to unknown place 'nowhere'",
        "{F}:9: transitions.go.when: syntax error: invalid syntax in 'start and lambda: 1'",
        "{F}:10: transitions.go.delay: bad duration '5 fortnights': expected a number with a "
        "unit (ns, us, ms, s, min, h), e.g. 10ms or 2s",
        "{F}:11: transitions.go.do[0]: unknown symbol 'siren' (not in {BAD}/io.yaml)",
        "{F}:11: transitions.go.do[1]: start is an input (%IX0.0); a program cannot write it",
    ],
}
YAML_SYNTAX = "{F}:4: YAML syntax error: expected ',' or '}', but got ':'"


def expected(name: str, lines: list[str]) -> list[str]:
    return [line.replace("{F}", str(BAD / name)).replace("{BAD}", str(BAD)) for line in lines]


def problems_of(name: str) -> list[str]:
    with pytest.raises(ProgramError) as info:
        compile_file(BAD / name)
    return [str(p) for p in info.value.problems]


@pytest.mark.parametrize("name", sorted(CORPUS))
def test_bad_program_reports_its_exact_problems(name: str) -> None:
    assert problems_of(name) == expected(name, CORPUS[name])


def test_every_corpus_file_is_tested() -> None:
    support = {"io.yaml", "io_safe_off.yaml"}
    xfailed = {"yaml_syntax.yaml", "huge_literal.yaml", "over_capacity.yaml"}
    assert {p.name for p in BAD.glob("*.yaml")} == set(CORPUS) | support | xfailed


def test_yaml_syntax_error_is_reported_with_its_line() -> None:
    assert expected("yaml_syntax.yaml", [YAML_SYNTAX])[0] in problems_of("yaml_syntax.yaml")


def test_yaml_syntax_error_is_the_only_problem() -> None:
    assert problems_of("yaml_syntax.yaml") == expected("yaml_syntax.yaml", [YAML_SYNTAX])


def test_huge_integer_literal_is_a_problem_not_a_crash() -> None:
    (line,) = problems_of("huge_literal.yaml")
    assert line.startswith(f"{BAD / 'huge_literal.yaml'}:9: transitions.go.when: ")


def test_initial_tokens_above_capacity_are_a_problem() -> None:
    (line,) = problems_of("over_capacity.yaml")
    assert line.startswith(f"{BAD / 'over_capacity.yaml'}:3: places.buffer")


def test_problem_format_without_a_yaml_path() -> None:
    with pytest.raises(ProgramError) as info:
        compile_file(BAD / "does_not_exist.yaml")
    assert str(info.value) == (f"{BAD / 'does_not_exist.yaml'}:0: cannot read program: "
                               "No such file or directory")


def test_a_guard_escape_never_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []

    def trap(*args: object, **kwargs: object) -> None:
        calls.append("called")
        raise AssertionError("program text ran")

    monkeypatch.chdir(tmp_path)  # `touch pwned` would create tmp_path/pwned
    monkeypatch.setattr(os, "system", trap)
    monkeypatch.setattr(builtins, "eval", trap)
    monkeypatch.setattr(builtins, "exec", trap)
    for name in ("guard_escape.yaml", "subnet_param_escape.yaml"):
        with pytest.raises(ProgramError):
            compile_file(BAD / name)
    monkeypatch.undo()
    assert calls == []
    assert not (tmp_path / "pwned").exists()


@pytest.mark.parametrize(
    ("text", "line"),
    [
        ("io_image: ../x.yaml\n", "{R}/net.yaml:1: io_image: path '../x.yaml' leaves the "
                                  "program directory"),
        ("io_image: /etc/passwd\n", "{R}/net.yaml:1: io_image: absolute path '/etc/passwd' is "
                                    "not allowed here"),
        ("io_image: io.yaml\nsubnets:\n  s: {net: ../../x.yaml}\n",
         "{R}/net.yaml:3: subnets.s.net: path '../../x.yaml' leaves the program directory"),
    ],
)
def test_referenced_files_stay_inside_the_root(text: str, line: str) -> None:
    """Programs downloaded over the network are compiled with a root they may not leave."""
    with pytest.raises(ProgramError) as info:
        compile_text(text, str(BAD / "net.yaml"), root=BAD)
    assert [str(p) for p in info.value.problems] == [line.replace("{R}", str(BAD))]


# -- good programs --------------------------------------------------------------------------


def test_example_programs_compile_with_subnets_expanded() -> None:
    transport = compile_file(PROGRAMS / "transport.yaml")
    assert transport.subnets == ("c1", "c2")
    assert {"c1.idle", "c1.moving", "c1.full", "c2.idle", "handing_over"} <= set(
        transport.place_names)
    start = transport.transition("c2.start")  # parameters substituted: a symbol, a literal
    assert start.guard is not None and start.guard.text == "s2_i and (not False)"
    feed = transport.transition("c1.start")  # the HMI's `hold` stops conveyor 1's feed only
    assert feed.guard is not None and feed.guard.reads == {"s1_i", "hold"}
    assert transport.moore_drivers["m1"]  # c1.moving and handing_over drive m1
    drilling = compile_file(PROGRAMS / "drilling.yaml")
    assert drilling.transition("drill").duration_ns == 2_000_000_000
    assert drilling.transition("taken").delay_ns == 200_000_000


def test_yaml_booleans_are_yaml_1_2(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(
        'symbols:\n  on: {address: "%IX0.0"}\n  q: {address: "%QX0.0", safe: true}\n',
        encoding="utf-8")
    net = compile_text("io_image: io.yaml\nplaces:\n  p: {tokens: 1}\n"
                       "transitions:\n  t: {from: [p], when: on and true}\n",
                       str(tmp_path / "p.yaml"))
    assert "on" in net.io.symbols  # the key `on` is a name, not true
    assert net.io.symbols["q"].safe == 1  # `true` is a boolean
    guard = net.transition("t").guard
    assert guard is not None and guard.reads == {"on"}
    # a guard that is exactly on/off/yes/no is refused, quoted or not: it is ambiguous
    with pytest.raises(ProgramError, match=r"guard 'on' \('on' is text here"):
        compile_text("io_image: io.yaml\nplaces:\n  p: {tokens: 1}\n"
                     "transitions:\n  t: {from: [p], when: \"on\"}\n", str(tmp_path / "p.yaml"))


# -- softplc check --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("program", "summary"),
    [
        ("transport.yaml", r"program transport: 8 places, 7 transitions, 18 arcs, 8 symbols, "
                           r"2 subnets \(hash [0-9a-f]{12}\)"),
        ("drilling.yaml", r"program drilling: 8 places, 7 transitions, 16 arcs, 10 symbols, "
                          r"0 subnets \(hash [0-9a-f]{12}\)"),
    ],
)
def test_check_prints_a_summary_and_exits_0(program: str, summary: str,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PROGRAMS / program)]) == 0
    out, err = capsys.readouterr()
    # The compiler's summary, then the analysis summary (issue 12): no finding, no warning.
    analysis = (r"analysis \(scan\): \d+ states, \d+ edges, bounded, 0 deadlock\(s\), "
                r"0 dead transition\(s\), 0 output conflict\(s\), [\d.]+ ms")
    assert re.fullmatch(summary + "\n" + analysis + "\n", out), out
    assert err == ""
    net = compile_file(PROGRAMS / program)
    assert out.splitlines()[0] == f"{summarize(net)}"


def test_check_prints_every_problem_and_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    name = "several_problems.yaml"
    assert main(["check", str(BAD / name)]) == 1
    out, err = capsys.readouterr()
    lines = expected(name, CORPUS[name])
    assert out == ""
    assert err.splitlines() == [*lines, f"{BAD / name}: {len(lines)} problem(s)"]


def test_check_as_a_command(tmp_path: Path) -> None:
    """The console entry point, as a person runs it, from another directory."""
    ok = subprocess.run([sys.executable, "-m", "softplc.cli", "check",
                         str(PROGRAMS / "transport.yaml")], capture_output=True, text=True,
                        cwd=tmp_path, timeout=60, check=False)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("program transport: 8 places")
    bad = subprocess.run([sys.executable, "-m", "softplc.cli", "check", "unknown_place.yaml"],
                         capture_output=True, text=True, cwd=BAD, timeout=60, check=False)
    assert bad.returncode == 1
    assert bad.stderr.splitlines() == [
        "unknown_place.yaml:7: transitions.go.to: arc to unknown place 'nowhere'",
        "unknown_place.yaml: 1 problem(s)",
    ]


# -- docs/programs.md -----------------------------------------------------------------------

DOCS = REPO / "docs" / "programs.md"


def doc_files() -> dict[str, str]:
    """The YAML blocks of docs/programs.md that start with `# <relative path>`."""
    blocks = re.findall(r"```yaml\n(.*?)```", DOCS.read_text(encoding="utf-8"), re.S)
    files = {}
    for block in blocks:
        first = block.splitlines()[0]
        if re.fullmatch(r"# (io_images|programs)/[\w/]+\.yaml", first):
            files[first[2:]] = block
    return files


def test_docs_examples_compile(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    files = doc_files()
    assert "io_images/cell.yaml" in files and "programs/nets/belt.yaml" in files
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text, encoding="utf-8")
    programs = sorted(rel for rel in files if re.fullmatch(r"programs/\w+\.yaml", rel))
    assert len(programs) >= 6
    for rel in programs:
        compile_file(tmp_path / rel)  # raises ProgramError with every problem
    assert main(["check", str(tmp_path / "programs/conveyor.yaml")]) == 0
    summary = capsys.readouterr().out.split(" (hash")[0]
    assert summary == "program conveyor: 2 places, 2 transitions, 4 arcs, 8 symbols, 0 subnets"
    assert summary in DOCS.read_text(encoding="utf-8")


def test_a_misspelt_token_field_is_a_located_problem_with_a_suggestion(tmp_path: Path) -> None:
    """Issue 16: fields are inferred from initial tokens and productions."""
    (tmp_path / "io.yaml").write_text('symbols:\n  q: {address: "%QX0.0", type: bool}\n')
    program = tmp_path / "m.yaml"
    program.write_text(
        "program: m\nio_image: io.yaml\nplaces:\n"
        "  a: {coloured: true, tokens: [{count: 0}]}\n  b: {coloured: true}\n"
        "transitions:\n  t:\n    from: [{place: a, var: x}]\n    to: [{place: b, token: x}]\n"
        "    when: x.count >= 3\n  u:\n    from: [{place: b, var: y}]\n"
        "    to: [{place: a, token: {count: \"y.cont + 1\"}}]\n")
    with pytest.raises(ProgramError) as caught:
        compile_file(program)
    (problem,) = caught.value.problems
    assert (problem.line, "y.cont" in problem.message) == (13, True)
    assert "did you mean 'count'" in problem.message
