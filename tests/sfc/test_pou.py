"""`--pou NAME` on every command that takes a program (issue 42 item 1): the same as the
program `FILE.xml#NAME`; a different `#POU` beside it, a YAML program, a PNML net or no program
are usage errors before anything runs; a file with several SFC POUs and none named lists them."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from softplc.cli import build_parser, main, parse
from softplc.cli.table import COMMANDS
from softplc.core.problems import ProgramError
from softplc.sfc.load import load_chart
from tests.sfc.chartxml import ChartSpec, chart_xml

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def two(tmp_path: Path) -> Path:
    """A PLCopen file with two SFC POUs, Chart and Other."""
    spec = ChartSpec(["Start", "Run"], ["Start"], [(["Start"], ["Run"], "go"),
                                                   (["Run"], ["Start"], "NOT go")],
                     variables={"go": ("BOOL", "%IX0.0"), "lamp": ("BOOL", "%QX0.0")})
    one = chart_xml(spec)
    pou = one[one.index("<pou "):one.index("</pou>") + 6]
    path = tmp_path / "two.xml"
    path.write_text(one.replace("</pous>", pou.replace('name="Chart"', 'name="Other"') +
                                "</pous>"), encoding="utf-8")
    return path


# Each command that takes a program, with its other required arguments; P is the program.
ARGV = {
    "check": ["check", "P"],
    "run": ["run", "P"],
    "simulate": ["simulate", "P"],
    "replay": ["replay", "trace.jsonl", "P"],
    "analyze": ["analyze", "P"],
    "import": ["import", "P", "-o", "out"],
    "export": ["export", "P", "-o", "out.pnml"],
    "why": ["why", "--trace", "trace.jsonl", "--program", "P"],
    "vcd": ["vcd", "trace.jsonl", "P", "-o", "out.vcd"],
    "download": ["download", "P"],
    "sign": ["sign", "P", "--key", "k"],
}


def _argv(command: str, program: str, *more: str) -> list[str]:
    return [program if a == "P" else a for a in ARGV[command]] + list(more)


@pytest.mark.parametrize("command", sorted(ARGV))
def test_pou_names_the_chart_as_file_hash_pou_does(command: str, two: Path) -> None:
    args = parse(_argv(command, str(two), "--pou", "Other"))
    assert getattr(args, COMMANDS[command].program) == f"{two}#Other"
    same = parse(_argv(command, f"{two}#other", "--pou", "Other"))  # POU names ignore case
    assert getattr(same, COMMANDS[command].program) == f"{two}#other"


def test_every_command_with_a_program_takes_pou() -> None:
    """A command added later with a program argument gets --pou by naming it in the table."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    with_program = {name for name, p in sub.choices.items()
                    if any(a.dest in ("program", "net", "chart") for a in p._actions)}
    assert with_program == set(ARGV) == {n for n, e in COMMANDS.items() if e.program}
    assert all("--pou" in sub.choices[n].format_help() for n in ARGV)


def test_check_and_import_run_the_named_pou(two: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(two), "--pou", "Other"]) == 0
    assert capsys.readouterr().out.startswith("program Other: 2 places")
    assert main(["check", str(two)]) == 1
    assert f"{two}:2: several SFC POUs (Chart, Other): name one with --pou POU or " \
        "FILE.xml#POU" in capsys.readouterr().err
    assert main(["import", str(two), "--pou", "other", "-o", str(tmp_path / "o")]) == 0
    assert (tmp_path / "o" / "Other.yaml").is_file()
    assert main(["check", str(two), "--pou", "Nope"]) == 1
    assert "no SFC POU named 'Nope'; SFC POUs in the file: Chart, Other" in \
        capsys.readouterr().err


def _usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    return capsys.readouterr().err


def test_what_cannot_mean_anything_is_a_usage_error(two: Path, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    err = _usage_error(["check", f"{two}#Chart", "--pou", "Other"], capsys)
    assert err.startswith("usage: softplc check")
    assert f"softplc check: error: --pou Other and {two}#Chart name different POUs (Other, " \
        "Chart): name it once" in err
    yaml = ROOT / "programs" / "drilling.yaml"
    assert f"softplc simulate: error: --pou Other: {yaml} is not a PLCopen XML file (.xml); " \
        "--pou names an SFC POU of one (a YAML program is one net)" in \
        _usage_error(["simulate", str(yaml), "--pou", "Other"], capsys)
    pnml = tmp_path / "net.xml"
    pnml.write_text('<pnml xmlns="http://www.pnml.org/version-2009/grammar/pnml"/>')
    assert f"softplc analyze: error: --pou Other: {pnml} is not a PLCopen TC6 project (no " \
        "PLCopen namespace: a PNML net?)" in _usage_error(["analyze", str(pnml), "--pou",
                                                            "Other"], capsys)
    assert "softplc why: error: --pou Other names an SFC POU of a program file: give the " \
        "program too (--program FILE.xml)" in _usage_error(["why", "--pou", "Other"], capsys)
    assert "softplc run: error: --pou Other names an SFC POU of a program file: give the " \
        "program too (PROGRAM FILE.xml)" in _usage_error(["run", "--pou", "Other"], capsys)


def test_the_loader_refuses_two_different_names_too(two: Path) -> None:
    with pytest.raises(ProgramError) as info:
        load_chart(f"{two}#Chart", "Other")
    assert "name different POUs" in str(info.value.problems[0])
    assert load_chart(f"{two}#Other", "OTHER").chart.pou == "Other"
