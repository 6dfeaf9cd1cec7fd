"""IEC 61131-3 time literals (T#5s, TIME#1m30s, LT#...) wherever softplc reads a duration: a
program's delay:/duration:, a simulation script's at:, a command line's --period and
--duration; one parser (core/units.py) for all of them (issue 39 item 5)."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.cli import main
from softplc.core.units import parse_duration_ns
from softplc.program.compiler import compile_file
from softplc.runtime.offline.simscript import load_script
from tests.runtime.test_simulate_script import IO, PROGRAM


@pytest.mark.parametrize(("text", "ns"), [
    ("T#5s", 5 * 10**9), ("t#250ms", 250 * 10**6), ("TIME#1m30s", 90 * 10**9),
    ("T#1h_2m_3s_500ms", 3_723_500_000_000), ("LT#1.5s", 1_500_000_000),
    ("LTIME#2d", 2 * 86_400 * 10**9), ("T#10us", 10_000), (" T#0s ", 0)])
def test_an_iec_time_is_a_duration(text: str, ns: int) -> None:
    assert parse_duration_ns(text) == ns


@pytest.mark.parametrize("text", ["T#", "T#5x", "T#-5s", "T#5s1m", "T#1.5ns", "T#5s5s"])
def test_a_bad_iec_time_says_what_to_write(text: str) -> None:
    with pytest.raises(ValueError, match=r"bad duration") as err:
        parse_duration_ns(text)
    assert repr(text) in str(err.value)


def test_a_script_and_the_command_line_take_iec_times(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "request.yaml").write_text(PROGRAM, encoding="utf-8")
    (tmp_path / "script.yaml").write_text(
        "- at: T#1s\n  force: {part: true}\n- at: TIME#2s\n  write: {request: true}\n"
        "- at: T#3s_500ms\n  release: [part]\n", encoding="utf-8")
    script = load_script(tmp_path / "script.yaml", compile_file(tmp_path / "request.yaml").io)
    assert [step.at_ns for step in script.steps] == [10**9, 2 * 10**9, 3_500_000_000]
    assert main(["simulate", str(tmp_path / "request.yaml"), "--duration", "T#5s",
                 "--period", "T#10ms", "--script", str(tmp_path / "script.yaml"),
                 "--timeline"]) == 0
    out = capsys.readouterr().out
    assert "fired: {'accept': 1, 'finish': 1}" in out
    assert "k=350 " in out  # the release at 3.5 s, scan 350 of 10 ms
