"""Diagnostics where people look (issue 16): a guard dividing by zero at run time is a located
diagnostic in plain `simulate` output, in status and in the trace; `replay` errors are one
line; a replay mismatch names the symbol."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from softplc.api.clicmds import format_status
from softplc.runtime.loop import LoopConfig, ScanLoop

IO = """symbols:
  q: {address: "%QX0.0", type: bool}
  w: {address: "%QW0", type: word}
"""
PROGRAM = """program: p
io_image: io.yaml
places:
  a: {coloured: true, tokens: [{n: 0}]}
  b: {}
  on: {outputs: [q]}
  off: {tokens: 1}
transitions:
  t:
    from: [{place: a, var: x}]
    to: [b]
    when: 10 // x.n > 1
  go:
    from: [off]
    to: [on]
"""


def softplc(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *args], capture_output=True,
                          text=True, timeout=60)


@pytest.fixture
def program(tmp_path: Path) -> Path:
    (tmp_path / "io.yaml").write_text(IO)
    path = tmp_path / "p.yaml"
    path.write_text(PROGRAM)
    return path


def test_a_guard_dividing_by_zero_is_a_diagnostic_in_plain_simulate_and_the_trace(
        program: Path, tmp_path: Path) -> None:
    trace = tmp_path / "t.jsonl"
    done = softplc("simulate", str(program), "--duration", "1s", "--trace", str(trace))
    assert done.returncode == 0, done.stderr
    lines = [line for line in done.stdout.splitlines() if "division by zero" in line]
    assert lines and f"{program}:9: transition t: guard '10 // x.n > 1'" in lines[0]
    assert "scan 0" in lines[0]
    assert "diagnostics: 1" in done.stdout
    assert "division by zero" in trace.read_text().splitlines()[0]


def test_status_counts_and_shows_the_diagnostic(program: Path) -> None:
    loop = ScanLoop(LoopConfig(program=str(program), start=True, max_scans=3,
                               period_ns=5_000_000, verify="off"), None, None)
    loop.run()
    document = loop.document()
    assert document["diagnostic_count"] == 1
    assert "division by zero" in format_status(document)
    assert any(e["name"].startswith("diagnostic:") for e in document["events"])


def test_replay_of_a_missing_trace_is_one_line(program: Path, tmp_path: Path) -> None:
    done = softplc("replay", str(tmp_path / "missing.jsonl"), str(program))
    assert done.returncode == 1
    assert done.stderr.strip().count("\n") == 0 and "missing.jsonl" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_replay_mismatch_names_the_symbol(program: Path, tmp_path: Path) -> None:
    trace = tmp_path / "t.jsonl"
    assert softplc("simulate", str(program), "--duration", "1s", "--trace",
                   str(trace)).returncode == 0
    program.write_text(PROGRAM.replace("on: {outputs: [q]}", "on: {}"))
    done = softplc("replay", str(trace), str(program))
    assert done.returncode == 1
    assert "q recorded 1, replay 0" in done.stderr
