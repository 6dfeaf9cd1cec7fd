"""Golden traces: every program in programs/ simulated for 120 s of virtual time, seed 0, on
the plant its io image declares; the trace's sha256 must equal the value in golden.json.

A golden value changes only when behaviour changes: the firing semantics, a program, an io
image, a plant model or the trace format. Refresh deliberately, after checking the new
behaviour is the intended one (e.g. with `softplc simulate PROGRAM --trace t.jsonl`):

    SOFTPLC_UPDATE_GOLDEN=1 .venv/bin/pytest tests/program/test_programs.py

then review and commit the diff of tests/program/golden.json with the change that caused it.
Beside each hash, tests/program/golden/NAME.txt shows the same run as text a reviewer can read
(the first EXCERPT_ROWS scans in which something happened: what fired, the marking's changes,
events, outputs that changed; then the totals), checked and refreshed the same way: a changed
hash comes with a readable diff of what changed.
"""

from __future__ import annotations

import json
import os
from functools import cache
from pathlib import Path
from typing import Any

import pytest

from softplc.program.compiler import compile_file
from softplc.runtime.offline.simulate import simulate

HERE = Path(__file__).resolve().parent
PROGRAMS = HERE.parent.parent / "programs"
GOLDEN = HERE / "golden.json"
EXCERPTS = HERE / "golden"
EXCERPT_ROWS = 40
DURATION_NS = 120 * 10**9
# Programs that run on simulated plants alone: a program whose io image drives other PLCs
# (programs/cell.yaml, over OPC UA) has no plant of its own to simulate; its closed loop with
# three real PLCs is tests/opcua/test_cell.py.
NAMES = sorted(p.name for p in PROGRAMS.glob("*.yaml")
               if all(d.kind == "sim" for d in compile_file(p).io.drivers.values()))


@cache
def run(name: str) -> dict[str, Any]:
    return simulate(compile_file(PROGRAMS / name), DURATION_NS, seed=0, timeline=True)


def golden() -> dict[str, str]:
    return json.loads(GOLDEN.read_text(encoding="utf-8")) if GOLDEN.exists() else {}


@pytest.mark.parametrize("name", NAMES)
def test_trace_matches_the_golden_value(name: str) -> None:
    sha = run(name)["trace_sha256"]
    if os.environ.get("SOFTPLC_UPDATE_GOLDEN") == "1":
        values = golden()
        values[name] = sha
        GOLDEN.write_text(json.dumps(values, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    assert name in golden(), f"no golden trace for {name}: see this module's docstring"
    assert sha == golden()[name], f"{name}: behaviour changed; see this module's docstring"


def excerpt(report: dict[str, Any]) -> str:
    """The run as a reviewer reads it."""
    def pairs(mapping: dict[str, Any]) -> str:
        return ", ".join(f"{k} {v}" for k, v in mapping.items())

    lines = [f"# {report['program']}: {report['scans']} scans of {report['period_ms']:g} ms, "
             f"seed {report['seed']}; trace sha256 {report['trace_sha256']}"]
    for row in report["timeline"][:EXCERPT_ROWS]:
        fired = " ".join(row.get("fired", ())) or "-"
        line = f"scan {row['k']:6d} {row['t_s']:8.2f} s  fired {fired}"
        line += f"  | done {' '.join(row['done'])}" if row.get("done") else ""
        line += f"  | marking {pairs(row['marking'])}" if row.get("marking") else ""
        line += f"  | events {' '.join(row['events'])}" if row.get("events") else ""
        line += f"  | outputs {pairs(row['changed'])}" if row.get("changed") else ""
        lines.append(line)
    lines.append(f"... {max(0, len(report['timeline']) - EXCERPT_ROWS)} more scans with changes")
    lines.append(f"fired in all: {pairs(report['fired'])}")
    lines.append(f"final marking: {pairs(report['marking'])}")
    lines.append(f"final outputs: {pairs(report['outputs_final'])}; state {report['state']}")
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("name", NAMES)
def test_the_readable_excerpt_matches_the_run(name: str) -> None:
    text = excerpt(run(name))
    path = EXCERPTS / f"{Path(name).stem}.txt"
    if os.environ.get("SOFTPLC_UPDATE_GOLDEN") == "1":
        EXCERPTS.mkdir(exist_ok=True)
        path.write_text(text, encoding="utf-8")
    assert path.exists(), f"no readable excerpt for {name}: see this module's docstring"
    assert text == path.read_text(encoding="utf-8"), f"{name}: behaviour changed; diff {path}"
    assert golden()[name] in text.splitlines()[0]  # the excerpt is of the golden run


@pytest.mark.parametrize("name", NAMES)
def test_two_runs_give_identical_results(name: str) -> None:
    first = run(name)
    second = simulate(compile_file(PROGRAMS / name), DURATION_NS, seed=0, timeline=True)
    assert second == first
    assert first["state"] == "RUNNING" and first["diagnostics"] == []
    assert sum(first["fired"].values()) > 0


def test_every_golden_value_belongs_to_a_program() -> None:
    assert sorted(golden()) == NAMES
