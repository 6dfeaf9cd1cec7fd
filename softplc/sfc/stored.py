"""Stored timed BOOL actions (SD, SL): IEC 61131-3's ACTION_CONTROL latch and timer.

Owns: the net pieces of one SD or SL association of a step and a BOOL, from the standard's
ACTION_CONTROL body (Ed.2 2.6.4.5, figure 15): SD_FF/SL_FF is an RS latch set while the step
is active and reset (dominant) while a step with an R of the same BOOL is active; a TON runs
on the latch, not on the step, so it outlives the step; SD's output is the TON's Q, SL's is
the latch AND NOT Q. In the net the latch is a memory BOOL `STEP_Q_VAR_latch`, set by every
transition entering the step (idempotent: a new activation while latched neither restarts
the timer nor, for SL, turns a run-out output on again: `VAR = VAR OR NOT latch`) and reset
by every transition entering an R step; the TON is one transition on an always-marked place
`STEP_Q_VAR` (a self-loop) whose guard is the latch (SD: and not yet VAR; SL: and VAR) with
`delay:` the duration, softplc's enabling delay being exactly a TON on its guard.
The latch is reset on entering an R step only, so the standard's "while active" is kept by
refusing (verify.py) a chart where the SD/SL step and an R step of its BOOL can be active at
once. Does not know: YAML (emit.py writes what this returns), XML.
"""

from __future__ import annotations

from softplc.core.problems import Problem
from softplc.sfc.model import Action, Chart, Transition

QUALIFIERS = ("SD", "SL")


def stored(chart: Chart) -> list[Action]:
    return [a for a in chart.actions if a.qualifier in QUALIFIERS and a.target]


def place(a: Action) -> str:
    return f"{a.step}_{a.qualifier}_{a.target}"


def latch(a: Action) -> str:
    return f"{place(a)}_latch"


def places(chart: Chart) -> list[tuple[str, str, int]]:
    return [(place(a), f"timer of action {a.target} ({a.qualifier} {a.duration}) of step "
             f"{a.step}, {chart.file}:{a.line}: always marked, the TON runs on the latch "
             f"{latch(a)}", a.line) for a in stored(chart)]


def latches(chart: Chart) -> list[tuple[str, Action]]:
    return [(latch(a), a) for a in stored(chart)]


def resetters(chart: Chart, a: Action) -> list[Action]:
    return [b for b in chart.actions if b.target == a.target and b.qualifier == "R"]


def on_enter(chart: Chart, entered: list[str]) -> list[tuple[str, str]]:
    """Set the latches of the entered SD/SL steps (SL's output on if it was not latched),
    then reset those an entered R step cancels."""
    out: list[tuple[str, str]] = []
    for a in stored(chart):
        if a.step in entered:
            if a.qualifier == "SL":
                out.append((f"{a.target} = {a.target} or not {latch(a)}", str(a.line)))
            out.append((f"set {latch(a)}", str(a.line)))
    for a in stored(chart):
        for r in resetters(chart, a):
            if r.step in entered:
                out.append((f"reset {latch(a)}", str(r.line)))
    return out


def transitions(chart: Chart) -> list[tuple[Transition, list[tuple[str, str]], bool]]:
    """The TON of each association: fires once the latch has held for the duration. The flag
    says whether its write goes before the chart's in a round (SD's `set`: an R step entered
    in that round resets after it) or after them (SL's `reset`: a new activation in that
    round keeps the BOOL as it was at the start of the round, and the run-out must win)."""
    out = []
    for a in stored(chart):
        p, x = place(a), a.target
        guard = f"{latch(a)} and not {x}" if a.qualifier == "SD" else f"{latch(a)} and {x}"
        write = f"set {x}" if a.qualifier == "SD" else f"reset {x}"
        out.append((Transition(f"{p}_elapsed", a.line, (p,), (p,), f"{latch(a)} held for "
                               f"{a.duration}", guard=guard, delay_ms=a.duration_ms),
                    [(write, str(a.line))], a.qualifier == "SD"))
    return out


def check(chart: Chart, problems: list[Problem]) -> None:
    """One SD/SL association per BOOL (R associations excepted), none on an initial step
    (no transition enters it at start, so nothing would set the latch)."""
    initial = {s.name for s in chart.steps if s.initial}
    for a in stored(chart):
        where = f"action {a.target} ({a.qualifier} {a.duration}) of step {a.step}"
        others = [b for b in chart.actions if b.target == a.target and b is not a
                  and b.qualifier != "R"]
        if others:
            b = others[0]
            problems.append(Problem(chart.file, a.line, "", f"{where}: {a.target} is also "
                            f"driven by {b.qualifier} in step {b.step} (line {b.line}); a stored "
                            "timed action must be the only one driving its BOOL (R excepted)"))
        if a.step in initial:
            problems.append(Problem(chart.file, a.line, "", f"{where}: on the initial step "
                            "no transition sets its latch; move it to a later step"))
