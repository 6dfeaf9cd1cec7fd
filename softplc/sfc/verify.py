"""The chart's token game before it runs: the SFC errors of IEC 61131-3 in the chart's terms.

Owns: exploring every situation (set of active steps) the chart can reach when any condition
may be true (conditions are not evaluated: only a constant FALSE is known never to clear),
and reporting, each with a witness (the transitions that lead there from the initial steps):
an unsafe chart (a step activated while active: two tokens in the net), unreachable steps,
transitions that can never clear, and deadlocks (a situation no transition leaves). A
situation whose active steps are all final steps (steps no transition leaves: the author
ended the chart there) is not a deadlock of the chart: it is a note, `final step S7: the
chart ends there`; the net's analysis gate still reports the dead marking, as for any net
(blocking under `--verify refuse`, a finding under `warn`).
Does not know: XML, YAML, the engine.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

from softplc.core.problems import Problem
from softplc.sfc.model import Chart, Transition
from softplc.sfc.stored import resetters, stored

MAX_SITUATIONS = 100_000  # the charts seen have at most a few hundred


def verify(chart: Chart, notes: list[Problem] | None = None) -> list[Problem]:
    """The chart's problems; the notes (final steps reached) go to `notes`."""
    index = {s.name: i for i, s in enumerate(chart.steps)}
    start = tuple(1 if s.initial else 0 for s in chart.steps)
    problems: list[Problem] = []

    def say(line: int, message: str) -> None:
        problems.append(Problem(chart.file, line, "", message))

    if not any(start):
        say(chart.pou_line, f"chart {chart.pou} has no initial step")
        return problems
    live = [t for t in chart.transitions if not t.never]
    parent: dict[tuple[int, ...], tuple[tuple[int, ...], str] | None] = {start: None}
    queue, fired, deadlocks = deque([start]), set[str](), list[tuple[int, ...]]()
    unsafe: tuple[tuple[int, ...], str] | None = None
    while queue and unsafe is None and len(parent) < MAX_SITUATIONS:
        m = queue.popleft()
        enabled = [t for t in live if _enabled(t, m, index)]
        if not enabled:
            deadlocks.append(m)
        for t in enabled:
            fired.add(t.name)
            nxt = list(m)
            for s in t.sources:
                nxt[index[s]] -= 1
            for s in t.targets:
                nxt[index[s]] += 1
            key = tuple(nxt)
            if key not in parent:
                parent[key] = (m, t.name)
                queue.append(key)
            if max(key) > 1:
                unsafe = (key, t.name)
                break
    path = _witness(parent)
    if unsafe is not None:
        key, t_name = unsafe
        steps = [s for s in chart.steps if key[index[s.name]] > 1]
        say(steps[0].line, f"unsafe chart: step {steps[0].name} is activated while it is "
            f"active (two tokens), by transition {t_name}; witness: {path(key)}")
        return problems
    if len(parent) >= MAX_SITUATIONS:
        say(chart.pou_line, f"more than {MAX_SITUATIONS} situations: not verified")
        return problems
    seen = {i for m in parent for i, n in enumerate(m) if n}
    for step in chart.steps:
        if index[step.name] not in seen:
            say(step.line, f"unreachable step {step.name}: no sequence of transitions from the "
                "initial steps activates it")
    for t in chart.transitions:
        if t.never:
            say(t.line, f"transition {t.name} can never clear: its condition is FALSE")
        elif t.name not in fired:
            say(t.line, f"transition {t.name} can never clear: its preceding steps "
                f"{', '.join(t.sources)} are never active together"
                + (f" with {', '.join(t.reads)} active" if t.reads else "")
                + (f" and {', '.join(t.inhibits)} inactive" if t.inhibits else ""))
    for a in stored(chart):
        for r in resetters(chart, a):
            both = next((m for m in parent if m[index[a.step]] and m[index[r.step]]), None)
            if both is not None:
                say(a.line, f"action {a.target} ({a.qualifier}) of step {a.step}: steps "
                    f"{a.step} and {r.step} (R {a.target}, line {r.line}) can be active "
                    "together, where IEC holds the latch reset while the R step is active "
                    f"(softplc resets it on entering the R step); witness: {path(both)}")
    final = {s.name for s in chart.steps} - {s for t in chart.transitions for s in t.sources}
    stuck = []
    for m in deadlocks:
        active = [s.name for s in chart.steps if m[index[s.name]]]
        if active and set(active) <= final:  # the author ended the chart there
            notes = notes if notes is not None else []
            notes.append(Problem(chart.file, chart.step_line(active[0]), "", f"final step"
                                 f"{'s' if len(active) > 1 else ''} {', '.join(active)}: the "
                                 f"chart ends there; witness: {path(m)}"))
        else:
            stuck.append((m, active))
    for m, active in stuck[:3]:
        say(chart.step_line(active[0]) if active else chart.pou_line,
            f"deadlock: once {', '.join(active) or 'no step'} "
            f"{'is' if len(active) == 1 else 'are'} active no transition can clear; "
            f"witness: {path(m)}")
    return problems


def _enabled(t: Transition, m: tuple[int, ...], index: dict[str, int]) -> bool:
    return all(m[index[s]] > 0 for s in t.sources) and \
        all(m[index[s]] > 0 for s in t.reads) and all(m[index[s]] == 0 for s in t.inhibits)


Situation = tuple[int, ...]


def _witness(parent: dict[Situation, tuple[Situation, str] | None]
             ) -> Callable[[Situation], str]:
    def path(m: tuple[int, ...]) -> str:
        names: list[str] = []
        link = parent.get(m)
        while link is not None:
            m, name = link
            names.append(name)
            link = parent.get(m)
        return " -> ".join(reversed(names)) or "(the initial steps)"
    return path
