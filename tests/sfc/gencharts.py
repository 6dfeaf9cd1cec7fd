"""Hypothesis strategies for well-formed SFC charts (safe, live) and their input sequences.

A chart is a loop of blocks from the initial step back to it: a plain step, a selection
divergence of 2-3 one-step branches, or a simultaneous divergence of 2 branches of 1-2 steps
joined again. Conditions are random ST over four BOOL inputs, sometimes `Step.T >= T#..`.
Actions: N on BOOL outputs, S/R on one output, P1/P0 pulses, ST bodies (N, P1, P0), each
body writing its own counter so the order of bodies within a scan cannot matter, and timed
L, D, DS, SD, SL actions on BOOLs of their own. Function blocks: one instance of each of
TON, TOF, TP, R_TRIG, F_TRIG (`F0`..`F4`), each called (or not) from one ST body (N, P1 or
P0) with a random IN/CLK (at times its own step's X) and its Q copied to a BOOL of its own;
conditions sometimes read `Fk.Q` (of a block that may never be called: Q stays FALSE).
"""

from __future__ import annotations

from hypothesis import strategies as st

from tests.sfc.chartxml import ChartSpec

INPUTS = ["i0", "i1", "i2", "i3"]
FBS = ["TON", "TOF", "TP", "R_TRIG", "F_TRIG"]
ATOMS = st.sampled_from([*INPUTS, "TRUE"])


@st.composite
def condition(draw: st.DrawFn, depth: int = 2) -> str:
    if depth == 0 or draw(st.booleans()):
        atom = draw(ATOMS)
        return f"NOT {atom}" if atom != "TRUE" and draw(st.booleans()) else atom
    op = draw(st.sampled_from(["AND", "OR", "XOR", "&", "="]))
    return f"({draw(condition(depth - 1))} {op} {draw(condition(depth - 1))})"


@st.composite
def charts(draw: st.DrawFn) -> ChartSpec:
    steps, trans = ["S0"], []
    current = "S0"
    names = iter(f"S{i}" for i in range(1, 100))

    def cond(step: str) -> str:
        pick = draw(st.integers(0, 6))
        if pick == 0:
            return f"{step}.T >= T#{draw(st.sampled_from([10, 20, 50]))}ms"
        if pick == 1:
            fb = f"F{draw(st.integers(0, len(FBS) - 1))}.Q"
            return fb if draw(st.booleans()) else f"({fb} OR {draw(condition(1))})"
        return draw(condition())

    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["step", "select", "parallel"]))
        if kind == "step":
            nxt = next(names)
            steps.append(nxt)
            trans.append(([current], [nxt], cond(current)))
        elif kind == "select":
            join = next(names)
            branches = [next(names) for _ in range(draw(st.integers(2, 3)))]
            steps += [*branches, join]
            for b in branches:
                trans.append(([current], [b], draw(condition())))
                trans.append(([b], [join], cond(b)))
        else:
            mid = next(names)
            steps.append(mid)
            trans.append(([current], [mid], cond(current)))
            heads = [next(names), next(names)]
            steps += heads
            tails = []
            for h in heads:
                if draw(st.booleans()):
                    t2 = next(names)
                    steps.append(t2)
                    trans.append(([h], [t2], cond(h)))
                    tails.append(t2)
                else:
                    tails.append(h)
            join = next(names)
            steps.append(join)
            trans.append(([mid], heads, draw(condition())))
            trans.append((tails, [join], draw(condition())))
            current = join
            continue
        current = steps[-1]
    trans.append(([current], ["S0"], cond(current)))
    return ChartSpec(steps, ["S0"], trans, *_actions(draw, steps))


def _actions(draw: st.DrawFn, steps: list[str]
             ) -> tuple[list[tuple[str, str, str]], dict[str, tuple[str, str]], dict[str, str]]:
    variables = {name: ("BOOL", f"%IX0.{i}") for i, name in enumerate(INPUTS)}
    variables |= {f"q{i}": ("BOOL", f"%QX0.{i}") for i in range(4)}
    actions: list[tuple[str, str, str]] = []
    bodies: dict[str, str] = {}
    for n, step in enumerate(steps):
        for _ in range(draw(st.integers(0, 2))):
            what = draw(st.sampled_from(["N0", "N1", "S", "R", "P1", "P0", "body"]))
            if what in ("N0", "N1"):
                actions.append((step, "N", f"q{what[1]}"))
            elif what in ("S", "R"):
                if not (what == "S" and step == "S0"):
                    actions.append((step, what, "q2"))
            elif what in ("P1", "P0"):
                if not (what == "P1" and step == "S0"):
                    actions.append((step, what, "q3"))
            else:
                qual = draw(st.sampled_from(["N", "P1", "P0"]))
                if qual == "P1" and step == "S0":
                    continue
                name, var = f"act{n}_{len(bodies)}", f"c{len(bodies)}"
                variables[var] = ("INT", f"%QW{len(bodies)}")
                bodies[name] = f"{var} := {var} + 1;"
                actions.append((step, qual, name))
    # Timed actions (L, D, DS, SD, SL), each on its own BOOL after S0 (one association per
    # BOOL); the stored ones are reset in S0, which no parallel branch overlaps.
    for i, qual in enumerate(("L", "D", "DS", "SD", "SL")):
        variables[f"t{i}"] = ("BOOL", f"%QX1.{i}")
        if len(steps) > 1 and draw(st.booleans()):
            step = draw(st.sampled_from(steps[1:]))
            ms = draw(st.sampled_from([10, 20, 50]))
            actions.append((step, f"{qual}@T#{ms}ms", f"t{i}"))
            if qual in ("DS", "SD", "SL"):
                actions.append(("S0", "R", f"t{i}"))
    for i, typ in enumerate(FBS):
        variables[f"F{i}"] = (f'derived name="{typ}"', "")
        variables[f"fq{i}"] = ("BOOL", f"%QX2.{i}")
        if draw(st.booleans()):
            qual = draw(st.sampled_from(["N", "N", "P1", "P0"]))
            step = draw(st.sampled_from(steps if qual != "P1" else steps[1:] or steps))
            inp = draw(st.sampled_from([draw(condition(1)), f"{step}.X",  # its own step
                                        f"({step}.X AND {draw(condition(1))})"]))
            arg = f"CLK := {inp}" if typ.endswith("TRIG") else \
                f"IN := {inp}, PT := T#{draw(st.sampled_from([10, 20, 50]))}ms"
            bodies[f"fb{i}"] = f"F{i}({arg}); fq{i} := F{i}.Q;"
            actions.append((step, qual, f"fb{i}"))
    return actions, variables, bodies


def inputs(scans: int) -> st.SearchStrategy[list[dict[str, bool]]]:
    one = st.fixed_dictionaries({name: st.booleans() for name in INPUTS})
    return st.lists(one, min_size=scans, max_size=scans)
