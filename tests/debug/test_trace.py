"""Why at a scan of a trace and the VCD export (issue 32, items 1 and 4): a simulated run of
the transport program recorded as a trace, explained scan by scan against what it fired, and
read back from VCD by a parser from PyPI (vcdvcd) with the trace's own values; the tank's VCD
with its reals and scaled symbols as values, to the run's end (issue 39, item 1)."""

from __future__ import annotations

import contextlib
import io
import json
import signal
from pathlib import Path
from typing import Any

import pytest

from softplc.cli import main
from softplc.core.why import FIRES, run_round, why
from softplc.debug.tracewalk import walk
from softplc.program.compiler import compile_file
from softplc.runtime.offline.simulate import simulate
from softplc.runtime.trace import read_trace

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = ROOT / "programs/transport.yaml"
TANK = ROOT / "programs/tank.yaml"
PERIOD_NS = 10_000_000


def read_vcd(path: Path) -> Any:
    """The file parsed by vcdvcd. Its import sets SIGPIPE to the default action (die) for the
    whole process, so that a later write to a closed socket in any test killed pytest: the
    handler is put back at once."""
    before = signal.getsignal(signal.SIGPIPE)
    try:
        from vcdvcd import VCDVCD
    finally:
        signal.signal(signal.SIGPIPE, before)
    return VCDVCD(str(path))


@pytest.fixture(scope="module")
def trace(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 s of the transport line: a part goes all the way through (take_off at ~11.6 s)."""
    path = tmp_path_factory.mktemp("trace") / "transport.jsonl"
    simulate(compile_file(PROGRAM), 12_000_000_000, PERIOD_NS, trace_path=path)
    return path


def cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return code, out.getvalue(), err.getvalue()


def test_why_says_fires_exactly_when_the_trace_fired(trace: Path) -> None:
    net = compile_file(PROGRAM)
    records = list(read_trace(trace))
    busy = {int(r["k"]) for r in records if r.get("fired")}
    # Every scan that fired something, the one before each, and every 50th.
    wanted = busy | {k - 1 for k in busy} | set(range(0, len(records), 50))
    checked = fired = 0
    for scanned in walk(trace, net, capture=wanted):
        cap = scanned.capture
        if cap is None:
            continue
        rnd = run_round(cap.net, cap.state, cap.ctx, cap.now_ns, cap.forced)
        for t in net.transitions:
            answer = why(rnd, t.name)
            assert answer.fires == (t.name in scanned.record.get("fired", [])), \
                (scanned.record["k"], t.name, answer)
            assert answer.reasons, (scanned.record["k"], t.name)
            checked += 1
            fired += answer.fires
    assert fired >= 7 and checked > 100


def test_softplc_why_at_a_scan_of_the_trace(trace: Path) -> None:
    records = {int(r["k"]): r for r in read_trace(trace)}
    hand_over = next(k for k, r in records.items() if "hand_over" in r.get("fired", []))
    code, out, err = cli("why", "hand_over", "--trace", str(trace), "--program", str(PROGRAM),
                         "--at-scan", str(hand_over))
    assert (code, err) == (0, "")
    assert out.splitlines()[:2] == [f"hand_over: fires (scan {hand_over})",
                                    "  - fires in this round"]
    code, out, _ = cli("why", "hand_over", "--trace", str(trace), "--program", str(PROGRAM),
                       "--at-scan", str(hand_over - 1), "--json")
    answer = json.loads(out)
    assert answer["verdict"] == "blocked" and answer["scan"] == hand_over - 1
    assert [r["text"] for r in answer["reasons"]] == ["c1.full: 0 of 1"]
    assert answer["feeders"][0]["transition"] == "c1.arrive"
    assert answer["feeders"][0]["verdict"] == FIRES  # its token is there one round later
    code, _, err = cli("why", "hand_ovr", "--trace", str(trace), "--program", str(PROGRAM),
                       "--at-scan", "3")
    assert code == 1 and "no transition 'hand_ovr'" in err
    code, _, err = cli("why", "hand_over", "--trace", str(trace), "--program", str(PROGRAM),
                       "--at-scan", "999999")
    assert code == 1 and "the trace has no scan 999999" in err


def value_at(tv: list[tuple[int, str]], t: int) -> int:
    """The value a VCD signal holds at time t (its last change at or before t)."""
    current = None
    for time, value in tv:
        if time > t:
            break
        current = value
    assert current is not None
    return int(current, 2)


def test_the_vcd_holds_the_traces_own_values(trace: Path, tmp_path: Path) -> None:
    out = tmp_path / "transport.vcd"
    code, said, err = cli("vcd", str(trace), str(PROGRAM), "-o", str(out))
    assert (code, err) == (0, "")
    records = list(read_trace(trace))
    assert said.strip() == f"vcd: {len(records)} scans of transport written to {out}"
    vcd = read_vcd(out)
    assert vcd.timescale["unit"] == "ns"
    net = compile_file(PROGRAM)
    by_location = {(s.address.attr, s.address.index): s.name for s in net.io.symbols.values()}

    def signal(name: str) -> Any:
        return vcd[f"transport.{name}" if name in net.io.symbols else
                   "transport.places." + name]

    compared = 0
    for record in records:
        t = int(record["t"])
        for area, values in record.get("in", {}).items():
            for index, value in values.items():
                name = by_location.get((area, int(index)))
                if name is not None:
                    assert value_at(signal(name).tv, t) == value, (record["k"], name)
                    compared += 1
        for name, value in {**record.get("q", {}), **record.get("m", {})}.items():
            assert value_at(signal(name).tv, t) == int(value), (record["k"], name)
            compared += 1
    assert compared > 30


def test_vcd_refuses_a_trace_of_another_program(trace: Path, tmp_path: Path) -> None:
    code, _, err = cli("vcd", str(trace), str(ROOT / "programs/drilling.yaml"),
                       "-o", str(tmp_path / "x.vcd"))
    assert code == 1 and "does not replay with program" in err


def test_the_tanks_vcd_carries_reals_and_engineering_units_to_the_runs_end(
        tmp_path: Path) -> None:
    trace, out = tmp_path / "tank.jsonl", tmp_path / "tank.vcd"
    simulate(compile_file(TANK), 25_000_000_000, PERIOD_NS, trace_path=trace)
    code, _, err = cli("vcd", str(trace), str(TANK), "-o", str(out))
    assert (code, err) == (0, "")
    records = list(read_trace(trace))
    assert "; units: level %, temperature °C $end" in out.read_text(encoding="utf-8")
    vcd = read_vcd(out)
    for name in ("fill_to", "min_temp", "level", "temperature"):
        assert vcd[f"tank.{name}"].var_type == "real", name
    assert vcd["tank.fill_to"].tv == [(0, "80.0")]  # init: 80.0, not its bits 1117782016
    assert vcd["tank.min_temp"].tv == [(0, "2.0")]
    compared = 0
    for record in records:
        t = int(record["t"])
        for index, raw in record.get("in", {}).get("iw", {}).items():
            name, eng = (("level", round(raw * 100 / 27648, 3)) if index == "0"
                         else ("temperature", round(raw / 10, 1)))  # 0..27648 = 0..100 %
            at = [float(v) for time, v in vcd[f"tank.{name}"].tv if time == t]
            assert at == [eng], (record["k"], name, raw)
            assert value_at(vcd[f"tank.{name}_raw"].tv, t) == raw
            compared += 1
    assert compared > 2000
    reached = next(int(r["t"]) for r in records if "reached" in r.get("fired", []))
    assert value_at(vcd["tank.places.run_on"].tv, reached) == 1
    assert float(value_at_text(vcd["tank.level"].tv, reached)) >= 80.0
    assert vcd.endtime == int(records[-1]["t"]) + PERIOD_NS  # the run's end, not its last change


def value_at_text(tv: list[tuple[int, str]], t: int) -> str:
    return [value for time, value in tv if time <= t][-1]
