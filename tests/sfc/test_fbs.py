"""Standard function blocks in SFC action bodies (issue 42): TON, TOF, TP, R_TRIG, F_TRIG called
in ST (`T1(IN := x, PT := T#30ms);`) and read as `T1.Q`, run on the real scan with the traces
IEC 61131-3's bodies give on the scan clock docs/sfc.md states (worked out by hand below);
calls without IN, a body reading an FB's Q in its own IN, and the refusals (located)."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from tests.core.helpers import Bench
from tests.sfc.chartxml import ChartSpec, chart_xml
from tests.sfc.compare import compare

MS = 1_000_000


def fb(typ: str) -> tuple[str, str]:
    return (f'derived name="{typ}"', "")  # chartxml writes <derived name="TON"/>


def _write(tmp_path: Path, body: str, extra: dict[str, tuple[str, str]] | None = None,
           cond: str = "i3") -> Path:
    spec = ChartSpec(["S0", "S1"], ["S0"], [(["S0"], ["S1"], cond), (["S1"], ["S0"], "TRUE")],
                     [("S0", "N", "body")],
                     {"i0": ("BOOL", "%IX0.0"), "i3": ("BOOL", "%IX0.3")}
                     | {f"q{k}": ("BOOL", f"%QX0.{k}") for k in range(6)} | (extra or {}),
                     {"body": body})
    path = tmp_path / "fbs.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    return path


def _run(path: Path, pattern: list[bool], outs: list[str]) -> dict[str, str]:
    bench = Bench(compile_file(path))  # scan 0 at t = 0: the first call, inputs 0
    seen = {q: str(bench.get(q)) for q in outs}
    for k, value in enumerate(pattern[1:], start=1):
        bench.set(i0=int(value))
        bench.scan(k * 10 * MS)
        for q in outs:
            seen[q] += str(bench.get(q))
    return seen


ALL = ("T1(IN := i0, PT := T#30ms); q0 := T1.Q; O1(IN := i0, PT := T#30ms); q1 := O1.Q;"
       "P1(IN := i0, PT := T#30ms); q2 := P1.Q; R1(CLK := i0); q3 := R1.Q;"
       "F1(CLK := i0); q4 := F1.Q;")
TYPES = {"T1": fb("TON"), "O1": fb("TOF"), "P1": fb("TP"), "R1": fb("R_TRIG"),
         "F1": fb("F_TRIG")}


def test_each_block_gives_the_iec_trace_on_the_scan_clock(tmp_path: Path) -> None:
    # IN (i0) on in scans 2-9 and 12-13, period 10 ms, PT 30 ms, called every scan. A timer
    # starts in the scan after the call that starts it (scan 3 for the rise at 2) and a call
    # compares PT with the time up to the scan before its own: TON's Q at 7 (a PLC: 5);
    # TOF off PT after the fall at 14 (counted from 15), at 19; TP on at 2 and 12 for 5 scans
    # (the second one runs out after IN fell); R_TRIG at the rises; F_TRIG at the falls and
    # at the very first call (IEC's M starts FALSE: Q = NOT CLK AND NOT M).
    pattern = [2 <= k <= 9 or 12 <= k <= 13 for k in range(22)]
    got = _run(_write(tmp_path, ALL, TYPES), pattern, ["q0", "q1", "q2", "q3", "q4"])
    assert got == {
        "q0": "0000000111000000000000",
        "q1": "0011111111111111111000",
        "q2": "0011111000001111100000",
        "q3": "0010000000001000000000",
        "q4": "1000000000100010000000",
    }
    assert compare(_write(tmp_path, ALL, TYPES), [{"i0": v} for v in pattern]) is None


def test_a_block_not_called_keeps_its_outputs(tmp_path: Path) -> None:
    # T1 is called in S0's body only; S0 is left (i3) while IN is on and T1 has not run out:
    # its final call (IEC's last execution of the N action) still sees Q off, and nothing
    # calls it after, so Q stays off (a PLC's TON that is not called does not update Q) even
    # though its time runs out in S1; back in S0 the next call sees the time run out.
    path = _write(tmp_path, "T1(IN := i0, PT := T#30ms); q0 := T1.Q;", {"T1": fb("TON")},
                  cond="i3 AND NOT T1.Q")
    spec_scans = [{"i0": k >= 1, "i3": k == 2} for k in range(12)]
    assert compare(path, spec_scans) is None
    bench = Bench(compile_file(path))
    memory = []
    for k, values in enumerate(spec_scans[1:], start=1):
        bench.set(**{n: int(v) for n, v in values.items()})
        bench.scan(k * 10 * MS)
        memory.append((bench.marking().get("S0", 0), bench.get("T1_Q")))
    # S0 left at 2, back at 3 (S1 -> S0 on TRUE): T1.Q on once a call sees PT run out.
    assert memory[:3] == [(1, 0), (0, 0), (1, 0)]
    assert memory[-1] == (1, 1)


def test_a_call_without_in_keeps_the_last_in_and_q_feeds_its_own_in(tmp_path: Path) -> None:
    # A self-restarting TON (IN := NOT T1.Q: a pulse every PT) reads the Q of the call before;
    # T2 is never given IN (one call site: IN stays as declared); F1 called again without
    # CLK in the same scan sees the CLK it had (no edge: Q FALSE, even at the first call).
    body = ("T1(IN := NOT T1.Q, PT := T#20ms); q0 := T1.Q; "
            "T2(PT := T#20ms); q1 := T2.Q; F1(CLK := i0); F1(); q2 := F1.Q;")
    path = _write(tmp_path, body, {"T1": fb("TON"), "T2": fb("TON"), "F1": fb("F_TRIG")})
    got = _run(path, [False] * 16, ["q0", "q1", "q2"])
    assert got["q2"] == "0" * 16  # F1() after F1(CLK := i0): the same CLK, no edge
    # T1: rise at 0, start at 1, Q at the call that sees 20 ms up to the scan before: 4;
    # IN falls (NOT Q) at 5, rises at 6, starts at 7, Q at 10: a pulse every 6 scans.
    assert got["q0"] == "0000100000100000"
    assert got["q1"] == "0" * 16  # IN never given: FALSE, as declared
    assert compare(path, [{"i0": False}] * 16) is None


def test_a_step_timer_on_its_own_step_x_restarts_with_each_activation(tmp_path: Path) -> None:
    # The IEC idiom `T1(IN := S1.X, PT := ...)` in S1's N body: X is TRUE while the body
    # runs and FALSE in its final execution (the scan S1 is left), so the TON is reset
    # there and starts over at the next activation. S1 entered at 1 (the first call, a
    # rise), T1 starts at 2, Q at the call of 6 (30 ms to the scan before), seen by the
    # condition at 7; entered again at 9, left at 15. With IN := TRUE instead the TON is
    # never reset, and the second visit would end at once (10).
    spec = ChartSpec(["S0", "S1", "S2"], ["S0"],
                     [(["S0"], ["S1"], "i0"), (["S1"], ["S2"], "T1.Q"), (["S2"], ["S1"], "i3")],
                     [("S1", "N", "body")],
                     {"i0": ("BOOL", "%IX0.0"), "i3": ("BOOL", "%IX0.3"),
                      "q0": ("BOOL", "%QX0.0"), "T1": fb("TON")},
                     {"body": "T1(IN := S1.X, PT := T#30ms); q0 := T1.Q;"})
    path = tmp_path / "steptimer.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    scans = [{"i0": k == 1, "i3": k == 9} for k in range(18)]
    assert compare(path, scans) is None
    bench, s1 = Bench(compile_file(path)), ""
    for k, values in enumerate(scans[1:], start=1):
        bench.set(**{n: int(v) for n, v in values.items()})
        bench.scan(k * 10 * MS)
        s1 += str(bench.marking().get("S1", 0))
    assert s1 == "11111100111111000", s1


@pytest.mark.parametrize(("body", "cond", "extra", "line_has"), [
    ("C1(CU := i0, PV := 3); q0 := C1.Q;", "i3", {"C1": fb("CTU")},
     "C1 is an instance of CTU: function blocks supported: TON, TOF, TP"),
    ("M1(IN := i0);", "i3", {"M1": fb("MyBlock")},
     "M1 is an instance of MYBLOCK"),
    ("T1(IN := i0, PT := T#1s);", "T1.ET >= T#500ms", {"T1": fb("TON")},
     "T1.ET: the elapsed time needs a clock"),
    ("T1(i0, T#1s);", "i3", {"T1": fb("TON")}, "arguments must be formal"),
    ("T1(IN := i0, PT := d);", "i3", {"T1": fb("TON"), "d": ("TIME", "")},
     "PT must be a positive TIME literal"),
    ("T1(IN := i0);", "i3", {"T1": fb("TON")}, "called without PT"),
    ("T1(IN := i0, PT := T#1s); T1(IN := NOT i0);", "i3", {"T1": fb("TON")},
     "called twice in one action body"),
    ("R1(IN := i0);", "i3", {"R1": fb("R_TRIG")}, "R_TRIG has the inputs CLK"),
    ("q0 := i0;", "T1(IN := i0)", {"T1": fb("TON")}, "a function block call is a statement"),
    ("q0 := T1;", "i3", {"T1": fb("TON")}, "read its output T1.Q"),
    ("q0 := S1.X;", "i3", {}, "reads S1.X: a body reads only its own step's X"),
    ("T1(IN := i0, PT := T#1s);", "i3", {"T1": fb("TON"), "T1_Q": ("BOOL", "")},
     "its state is kept in T1_Q"),
])
def test_what_does_not_map_is_refused_where_it_is_written(
        tmp_path: Path, body: str, cond: str, extra: dict[str, tuple[str, str]],
        line_has: str) -> None:
    path = _write(tmp_path, body, extra, cond)
    with pytest.raises(ProgramError) as info:
        compile_file(path)
    text = str(info.value)
    assert line_has in text, text
    assert f"{path}:" in text  # file:line


def test_an_instance_called_from_two_actions_is_refused(tmp_path: Path) -> None:
    spec = ChartSpec(["S0", "S1"], ["S0"], [(["S0"], ["S1"], "i3"), (["S1"], ["S0"], "TRUE")],
                     [("S0", "N", "a"), ("S1", "N", "b")],
                     {"i0": ("BOOL", "%IX0.0"), "i3": ("BOOL", "%IX0.3"), "T1": fb("TON")},
                     {"a": "T1(IN := i0, PT := T#1s);", "b": "T1(IN := NOT i0, PT := T#1s);"})
    path = tmp_path / "two.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    with pytest.raises(ProgramError, match="call an instance from one action"):
        compile_file(path)


def test_an_n_body_runs_in_the_scan_its_step_loops_on_itself(tmp_path: Path) -> None:
    # A transition from S0 back to S0 leaves the step active: its N body (and the calls in
    # it) runs in that scan as in every other (the net's self-loop cannot fire then).
    spec = ChartSpec(["S0", "S1"], ["S0"],
                     [(["S0"], ["S0"], "i0"), (["S0"], ["S1"], "i3"), (["S1"], ["S0"], "TRUE")],
                     [("S0", "N", "body")],
                     {"i0": ("BOOL", "%IX0.0"), "i3": ("BOOL", "%IX0.3"),
                      "c": ("INT", "%QW0"), "R1": fb("R_TRIG"), "q0": ("BOOL", "%QX0.0")},
                     {"body": "c := c + 1; R1(CLK := i0); q0 := R1.Q;"})
    path = tmp_path / "loop.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    scans = [{"i0": k == 3, "i3": False} for k in range(6)]
    assert compare(path, scans) is None
    bench = Bench(compile_file(path))
    for k, values in enumerate(scans[1:], start=1):
        bench.set(**{n: int(v) for n, v in values.items()})
        bench.scan(k * 10 * MS)
        assert (bench.get("c"), bench.get("q0")) == (k + 1, int(k == 3)), k
