"""IEC 61131-3 habits in YAML programs (issue 39, item 5): each mistake is one located
problem with what to write, and what IEC means the same as softplc is read (docs/programs.md,
"Expressions" and "Types"); problems in the symbols file name it as the program was named."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file

IO = """symbols:
  start: {address: "%IX0.0", type: bool}
  lamp:  {address: "%QX0.0", type: bool}
  count: {address: "%MW0", type: int}
"""


@pytest.fixture(autouse=True)
def _in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # programs named relative, as `softplc check p.yaml` names them


def problems_of(tmp_path: Path, program: str, io: str = IO) -> list[str]:
    (tmp_path / "io.yaml").write_text(io)
    (tmp_path / "p.yaml").write_text("io_image: io.yaml\n" + program)
    try:
        compile_file("p.yaml")
    except ProgramError as exc:
        return [str(p) for p in exc.problems]
    return []


NET = """places:
  idle: {tokens: 1}
  busy: {}
transitions:
  go:
    from: [idle]
    to: [busy]
"""


def test_iec_durations_are_read(tmp_path: Path) -> None:
    assert problems_of(tmp_path, NET + "    when: start AND NOT lamp\n    delay: T#1m30s\n"
                       "    duration: TIME#1h_2m_3s_500ms\n    outputs: [lamp]\n"
                       "    do: ['count := count MOD 4']\n") == []
    (tmp_path / "p.yaml").write_text("io_image: io.yaml\n" + NET + "    delay: t#1m30s\n"
                                     "    duration: T#250ms\n")
    net = compile_file(tmp_path / "p.yaml")
    go = net.transitions[0]
    assert (go.delay_ns, go.duration_ns) == (90 * 10**9, 250 * 10**6)


def test_a_bad_duration_is_one_problem_not_two(tmp_path: Path) -> None:
    # before: also "outputs: on a transition need a duration" for the same mistake
    assert problems_of(tmp_path, NET + "    duration: T#5x\n    outputs: [lamp]\n") == [
        "p.yaml:9: transitions.go.duration: bad duration 'T#5x': an IEC time is T# and units "
        "from days to nanoseconds, largest first, e.g. T#5s, T#1m30s, T#1h_2m, T#250ms; or "
        "write 5s, 90s, 250ms"]
    assert problems_of(tmp_path, NET + "    duration: 5 parsecs\n    outputs: [lamp]\n") == [
        "p.yaml:9: transitions.go.duration: bad duration '5 parsecs': expected a number with a "
        "unit (ns, us, ms, s, min, h), e.g. 10ms or 2s"]


def test_xor_gets_one_hint(tmp_path: Path) -> None:
    assert problems_of(tmp_path, NET + "    when: start XOR lamp\n") == [
        "p.yaml:9: transitions.go.when: XOR is not in the language (no operator has its IEC "
        "precedence): for bools write a != b, for integer bits a ^ b in 'start XOR lamp'"]


@pytest.mark.parametrize(("written", "meant"), [("REAL", "real"), ("BOOL", "bool"),
                                                ("Int", "int"), ("DINT", "dint")])
def test_upper_case_type_names_get_a_did_you_mean(tmp_path: Path, written: str,
                                                  meant: str) -> None:
    io = IO.replace("address: \"%MW0\", type: int", f"address: \"%MD0\", type: {written}")
    found = problems_of(tmp_path, NET, io)
    assert len(found) == 1 and found[0].startswith("io.yaml:4: symbols.count.type: unknown type")
    assert found[0].endswith(f"(did you mean {meant!r}?)")


def test_an_unquoted_address_is_located_and_the_other_problems_still_reported(
        tmp_path: Path) -> None:
    io = IO.replace('"%IX0.0", type: bool', "%IX0.0, type: bool").replace(
        '"%MW0", type: int', "%MW0, type: INT")
    assert problems_of(tmp_path, NET, io) == [
        'io.yaml:2: unquoted %IX0.0: YAML reserves % at the start of a value; write "%IX0.0"',
        'io.yaml:4: unquoted %MW0: YAML reserves % at the start of a value; write "%MW0"',
        "io.yaml:4: symbols.count.type: unknown type 'INT'; expected one of bool, int, word, "
        "dint, udint, real, lreal (did you mean 'int'?)"]


def test_symbols_file_problems_name_it_as_the_program_is_named(tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "io.yaml").write_text(IO.replace("type: int", "type: integer"))
    (tmp_path / "sub" / "p.yaml").write_text("io_image: ../sub/io.yaml\n" + NET)
    with pytest.raises(ProgramError) as err:
        compile_file("sub/p.yaml")
    assert [p.file for p in err.value.problems] == ["sub/io.yaml"]  # before: absolute


def test_why_names_the_false_part_of_an_iec_guard_as_written(tmp_path: Path) -> None:
    from softplc.core.net import NetState
    from softplc.core.why import explain
    from tests.debug.nets import compile_net, context

    net = compile_net(tmp_path, """
places: {p: {tokens: 1}}
transitions:
  go: {from: [p], when: "NOT a AND level MOD 4 = 3"}
""")
    why = explain(net, NetState.initial(net), context(net, a=1, level=2), 0, "go")
    # before: "~a" and "level @ 4 == 3" did not compile again, and were left out
    assert [r.text for r in why.reasons] == [
        "guard NOT a AND level MOD 4 = 3: NOT a is false with a = 1",
        "guard NOT a AND level MOD 4 = 3: level MOD 4 == 3 is false with level = 2"]
