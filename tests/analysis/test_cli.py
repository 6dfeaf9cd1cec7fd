"""`softplc analyze`, `softplc export` and the summary of `softplc check`, as a person runs
them (a real process for analyze --json on a PNML file)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from softplc.analysis.models import kanban, philosophers
from softplc.analysis.pnml import export_pt
from softplc.bench.analysisbench import ours, snakes_states
from softplc.cli import main

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = Path(__file__).resolve().parent / "programs"


def test_analyze_pnml_json_in_a_process(tmp_path: Path) -> None:
    net = tmp_path / "kanban1.pnml"
    net.write_text(export_pt(kanban(1)), encoding="utf-8")
    out = subprocess.run([sys.executable, "-m", "softplc.cli", "analyze", str(net), "--json",
                          "--semantics", "interleaving"], capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    for key in ("states", "edges", "complete", "bounded", "place_bounds", "max_tokens_place",
                "max_tokens_marking", "deadlocks", "dead_transitions", "output_conflicts",
                "p_invariants", "t_invariants", "seconds"):
        assert key in d
    assert (d["states"], d["edges"], d["complete"], d["bounded"]) == (160, 616, True, True)


def test_check_prints_findings_as_warnings_and_keeps_exit_0(
        capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PROGRAMS / "conflict.yaml")]) == 0
    out = capsys.readouterr().out
    assert "analysis (scan)" in out and "warning: " in out and "output motor" in out
    assert main(["check", str(ROOT / "programs" / "drilling.yaml")]) == 0
    assert "warning" not in capsys.readouterr().out


def test_analyze_exit_codes(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", str(ROOT / "programs" / "transport.yaml")]) == 0
    assert main(["analyze", str(PROGRAMS / "unbounded.yaml")]) == 1
    assert "place buffer: unbounded" in capsys.readouterr().out
    assert main(["analyze", str(ROOT / "programs" / "transport.yaml"), "--max-states", "2"]) == 2


def test_export_then_analyze_the_pnml(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "sub" / "transport.pnml"
    out.parent.mkdir()
    assert main(["export", str(ROOT / "programs" / "transport.yaml"), "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["analyze", str(out), "--json"]) == 0
    yaml_d = json.loads(capsys.readouterr().out)
    assert main(["analyze", str(ROOT / "programs" / "transport.yaml"), "--json"]) == 0
    prog_d = json.loads(capsys.readouterr().out)
    assert (yaml_d["states"], yaml_d["edges"]) == (prog_d["states"], prog_d["edges"])
    assert yaml_d["semantics"] == "scan"


def test_bad_pnml_exits_1_with_a_located_problem(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.pnml"
    bad.write_text("<pnml>\n<net>\n</pnml>\n")
    assert main(["analyze", str(bad)]) == 1
    assert f"{bad}:3: " in capsys.readouterr().err


@pytest.mark.parametrize("net", [kanban(1), philosophers(5)])
def test_snakes_state_graph_agrees(net) -> None:  # type: ignore[no-untyped-def]
    assert snakes_states(net)[0] == ours(net)[0]
