"""Timed BOOL actions (L, D, DS) as a timer place per action association.

Owns: the net pieces of IEC 61131-3's ACTION_CONTROL timers for one step and one BOOL: the
transitions entering the step put a token in the action's timer place `STEP_Q_VAR`; the
timer transition takes it once the step has been active for the duration (`read: [STEP]`,
`delay:`), the cleanup takes it when the step was left first (`inhibit: [STEP]`). What each
qualifier writes: L sets on entry, resets at the timer and on leaving; D sets at the timer,
resets on leaving; DS sets at the timer (stored until an R), and a leaving transition writes
the value the BOOL had at the start of the round, so a timer that runs out in the very round
the step is left does not store (IEC evaluates the action control after the clearing).
Does not know: YAML (emit.py writes what this returns), XML.
"""

from __future__ import annotations

from softplc.core.problems import Problem
from softplc.sfc.model import Action, Chart, Transition

QUALIFIERS = ("L", "D", "DS")


def timed(chart: Chart) -> list[Action]:
    return [a for a in chart.actions if a.qualifier in QUALIFIERS and a.target]


def place(a: Action) -> str:
    return f"{a.step}_{a.qualifier}_{a.target}"


def places(chart: Chart) -> list[tuple[str, str, int]]:
    return [(place(a), f"timer of action {a.target} ({a.qualifier} {a.duration}) of step "
             f"{a.step}, {chart.file}:{a.line}", a.line) for a in timed(chart)]


def entered_places(chart: Chart, entered: list[str]) -> list[str]:
    return [place(a) for a in timed(chart) if a.step in entered]


def on_leave(chart: Chart, left: list[str]) -> list[tuple[str, str]]:
    return [(f"reset {a.target}" if a.qualifier in ("L", "D") else f"{a.target} = {a.target}",
             str(a.line)) for a in timed(chart) if a.step in left]


def on_enter(chart: Chart, entered: list[str]) -> list[tuple[str, str]]:
    return [(f"set {a.target}", str(a.line)) for a in timed(chart)
            if a.step in entered and a.qualifier == "L"]


def transitions(chart: Chart) -> list[tuple[Transition, list[tuple[str, str]]]]:
    """The timer and the cleanup of every timed action; the caller gives them a priority
    above the chart's, so that a leaving transition's write in the same round comes last."""
    out = []
    for a in timed(chart):
        p = place(a)
        write = f"reset {a.target}" if a.qualifier == "L" else f"set {a.target}"
        out.append((Transition(f"{p}_elapsed", a.line, (p,), (), f"{a.step} active for "
                               f"{a.duration}", reads=(a.step,), delay_ms=a.duration_ms),
                    [(write, str(a.line))]))
        out.append((Transition(f"{p}_dropped", a.line, (p,), (), f"{a.step} left before "
                               f"{a.duration}", inhibits=(a.step,)), []))
    return out


def check(chart: Chart, problems: list[Problem]) -> None:
    """One action association per timed BOOL (an R of a DS one excepted), none on an initial
    step (no transition enters it at start), none on a step a transition re-enters directly
    (the step stays marked, so its timer would not start over)."""
    initial = {s.name for s in chart.steps if s.initial}
    loops = {s for t in chart.transitions for s in t.sources if s in t.targets}
    for a in timed(chart):
        where = f"action {a.target} ({a.qualifier} {a.duration}) of step {a.step}"
        others = [b for b in chart.actions if b.target == a.target and b is not a
                  and not (a.qualifier == "DS" and b.qualifier == "R")]
        if others:
            b = others[0]
            problems.append(Problem(chart.file, a.line, "", f"{where}: {a.target} is also "
                            f"driven by {b.qualifier} in step {b.step} (line {b.line}); a timed "
                            "action must be the only one driving its BOOL (R of a DS excepted)"))
        if a.step in initial:
            problems.append(Problem(chart.file, a.line, "", f"{where}: on the initial step "
                            "no transition starts its timer; move it to a later step"))
        if a.step in loops:
            problems.append(Problem(chart.file, a.line, "", f"{where}: a transition leaves "
                            f"{a.step} and enters it again in one clearing; its timer would not "
                            "start over"))
