"""Work a step at a time (core/steps.py): the engine, its priming and the carry plan built
stepwise are exactly what the plain calls build, in many short steps for a big net."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.core import online
from softplc.core.engine import Engine
from softplc.core.engine.enabling import Primed
from softplc.core.engine.tables import TABLE_STEP
from softplc.core.net import CompiledNet, NetState
from softplc.core.steps import STEP, drain
from softplc.program.compiler import compile_file, compile_text

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = sorted((ROOT / "programs").glob("*.yaml"))


def ring(transitions: int, spare: int = 0) -> str:
    lines = ["program: ring", "io_image: ../io_images/transport.yaml", "places:",
             "  p0: {tokens: 1}", *(f"  p{i}: {{}}" for i in range(1, transitions)),
             *(f"  spare{i}: {{tokens: 2}}" for i in range(spare)), "transitions:"]
    lines += [f"  t{i}: {{from: [p{i}], to: [p{(i + 1) % transitions}]"
              + (", when: s1_i" if i % 3 == 0 else "") + (", priority: 2" if i % 5 == 0 else "")
              + "}" for i in range(transitions)]
    return "\n".join(lines) + "\n"


def counted(steps: Any) -> tuple[Any, int]:
    n = 0
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value, n
        n += 1


def fields(part: object) -> dict[str, Any]:
    """Every attribute of an engine or one of its parts."""
    names = [n for cls in type(part).__mro__ for n in getattr(cls, "__slots__", ())]
    return {n: getattr(part, n) for n in names if hasattr(part, n)} | getattr(part, "__dict__", {})


def same_engine(a: object, b: object, path: str = "engine",
                seen: set[int] | None = None) -> None:
    """Two engines (or two of their parts) hold equal values, part by part."""
    seen = set() if seen is None else seen
    if id(a) in seen:  # a part several others share (the live state, the tables)
        return
    seen.add(id(a))
    left, right = fields(a), fields(b)
    assert left and left.keys() == right.keys(), path
    for name, x in left.items():
        y, where = right[name], f"{path}.{name}"
        if type(x).__module__.startswith("softplc.core.engine."):
            assert type(x) is type(y), where
            if isinstance(x, Primed):
                assert np.array_equal(x.marking, y.marking), where
                assert (x.ready, x.others) == (y.ready, y.others), where
            else:
                same_engine(x, y, where, seen)
        elif isinstance(x, CompiledNet):
            assert x is y, where
        elif isinstance(x, NetState):
            assert np.array_equal(x.marking, y.marking), where
            assert (x.tokens, x.enabled_since, x.busy) == (y.tokens, y.enabled_since, y.busy)
        elif isinstance(x, np.ndarray):
            assert np.array_equal(x, y), where
        elif name == "rank_key":  # a bound method of the rank list
            assert (x is None) == (y is None), where
        elif name not in ("_m", "_marr"):  # the view of the marking compared above
            assert x == y, where


def test_every_shipped_program_gets_the_same_engine_stepwise() -> None:
    for path in PROGRAMS:
        net = compile_file(path)
        plain = Engine(net, NetState.initial(net))
        plain.prime()
        stepped = drain(Engine.stepwise(net, NetState.initial(net)))
        drain(stepped.priming())
        same_engine(plain, stepped)
        for other in PROGRAMS:  # a replacement (another name) or the same net again
            before = compile_file(other)
            same_plan_as_by_names(online.plan(before, net), before, net)


@settings(max_examples=15, deadline=None)
@given(st.integers(2, 700), st.integers(0, 3))
def test_a_ring_built_stepwise_runs_as_the_plain_engine(transitions: int, spare: int) -> None:
    net = compile_text(ring(transitions, spare), str(ROOT / "programs" / "ring.yaml"), ROOT)
    plain = Engine(net, NetState.initial(net))
    stepped, steps = counted(Engine.stepwise(net, NetState.initial(net)))
    same_engine(plain, stepped)
    assert steps >= transitions // TABLE_STEP
    old = compile_text(ring(max(2, transitions // 2)), str(ROOT / "programs" / "ring.yaml"),
                       ROOT)
    for before, after in ((old, net), (net, old)):  # places added, then dropped
        a, (b, _) = online.plan(before, after), counted(online.planning(before, after))
        assert a.transitions == b.transitions and a.coloured == b.coloured
        for field in ("old_idx", "new_idx", "dropped", "fresh"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), field
        same_plan_as_by_names(a, before, after)


def same_plan_as_by_names(plan: online.CarryPlan, old: Any, new: Any) -> None:
    """The carry plan against its rules spelled out plainly (core/online.py): a place is kept
    when the new net has one of its name and colouredness, else dropped; the new places
    nobody kept are fresh; transitions are matched by name."""
    index = {name: q for q, name in enumerate(new.place_names)}
    kept = [(p, index[name]) for p, name in enumerate(old.place_names)
            if name in index and bool(old.coloured[p]) == bool(new.coloured[index[name]])]
    assert plan.old_idx.tolist() == [p for p, _ in kept]
    assert plan.new_idx.tolist() == [q for _, q in kept]
    assert plan.dropped.tolist() == sorted(set(range(len(old.place_names)))
                                           - {p for p, _ in kept})
    assert plan.fresh.tolist() == sorted(set(range(len(new.place_names)))
                                         - {q for _, q in kept})
    assert plan.coloured == tuple((p, q) for p, q in kept if old.coloured[p])
    names = {t.name: t.index for t in new.transitions}
    assert plan.transitions == {t.index: names[t.name] for t in old.transitions
                                if t.name in names}
    assert all(a.dtype == np.int64 for a in (plan.old_idx, plan.new_idx, plan.dropped,
                                             plan.fresh))


def test_a_big_net_is_built_in_short_steps() -> None:
    net = compile_text(ring(5000), str(ROOT / "programs" / "ring.yaml"), ROOT)
    _, table_steps = counted(Engine.stepwise(net, NetState.initial(net)))
    engine = Engine(net, NetState.initial(net))
    _, prime_steps = counted(engine.priming())
    _, plan_steps = counted(online.planning(net, net))
    assert table_steps >= 5000 // TABLE_STEP and prime_steps >= 5000 // STEP
    assert plan_steps >= 3 * 5000 // STEP
