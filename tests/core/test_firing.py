"""One firing round (docs/design.md section 3): hypothesis properties on random small nets, then
unit tests of each rule.

Random nets are generated as program text and compiled by the real compiler; the oracle below
works on the generated arc tables, not on the compiled net, so it checks the compiler too.
Nothing here opens a socket or sleeps: time is the `now_ns` argument.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softplc.core.engine import Engine, Step, enabled_transitions, fire_one
from softplc.core.image import parse_address
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet, NetState
from softplc.core.plc import ProgramCommand
from softplc.core.problems import PlcFault
from softplc.core.snapshot import HmiWrite
from softplc.program.compiler import compile_text
from tests.core.helpers import Bench, Ctx, compile_program, write_io

GUARDS = {
    None: lambda a, b: True,
    "a": lambda a, b: a,
    "not a": lambda a, b: not a,
    "b": lambda a, b: b,
    "a and not b": lambda a, b: a and not b,
    "a or b": lambda a, b: a or b,
}
START = ProgramCommand(Command.START)
PROPERTY = settings(max_examples=60, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def io_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("nets")
    write_io(directory)
    return directory


# -- random nets ----------------------------------------------------------------------------


@dataclass(frozen=True)
class Trans:
    pre: dict[int, int]
    post: dict[int, int]
    read: dict[int, int]
    inhibit: dict[int, int]
    priority: int
    guard: str | None


@dataclass(frozen=True)
class Gen:
    """A generated uncoloured net: the oracle's view of it."""

    tokens: tuple[int, ...]
    capacity: tuple[int | None, ...]
    transitions: tuple[Trans, ...]

    def text(self) -> str:
        lines = ["places:"]
        for p, n in enumerate(self.tokens):
            cap = "" if self.capacity[p] is None else f", capacity: {self.capacity[p]}"
            lines.append(f"  p{p}: {{tokens: {n}{cap}}}")
        lines.append("transitions:")
        for i, t in enumerate(self.transitions):
            lines.append(f"  t{i}:")
            for key, arcs in (("from", t.pre), ("to", t.post), ("read", t.read),
                              ("inhibit", t.inhibit)):
                if arcs:
                    inner = ", ".join(f"p{p}: {w}" for p, w in sorted(arcs.items()))
                    lines.append(f"    {key}: {{{inner}}}")
            lines.append(f"    priority: {t.priority}")
            if t.guard is not None:
                lines.append(f'    when: "{t.guard}"')
        return "\n".join(lines) + "\n"

    def compile(self, directory: Path) -> CompiledNet:
        net = compile_text("io_image: io.yaml\n" + self.text(), str(directory / "gen.yaml"))
        assert net.place_names == tuple(f"p{p}" for p in range(len(self.tokens)))
        return net

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        pre = np.zeros((len(self.tokens), len(self.transitions)), np.int64)
        post = np.zeros_like(pre)
        for i, t in enumerate(self.transitions):
            for p, w in t.pre.items():
                pre[p, i] = w
            for p, w in t.post.items():
                post[p, i] = w
        return pre, post

    def order(self) -> list[int]:
        return sorted(range(len(self.transitions)),
                      key=lambda i: (-self.transitions[i].priority, i))

    def enabled(self, i: int, m: Sequence[int], a: bool, b: bool) -> bool:
        t = self.transitions[i]
        return (all(m[p] >= w for p, w in t.pre.items())
                and all(m[p] >= w for p, w in t.read.items())
                and all(m[p] < w for p, w in t.inhibit.items())
                and self.fits_capacity(t, m, {})
                and GUARDS[t.guard](a, b))

    def fits_capacity(self, t: Trans, m: Sequence[int], delta: dict[int, int]) -> bool:
        for p, w in t.post.items():
            cap = self.capacity[p]
            if cap is not None and m[p] + delta.get(p, 0) - t.pre.get(p, 0) + w > cap:
                return False
        return True

    def greedy(self, m: Sequence[int], a: bool, b: bool) -> list[int]:
        """The step by the rule of docs/design.md section 3: walk the candidates by priority, then
        declaration order; take each that still fits the residual marking."""
        residual = list(m)
        delta: dict[int, int] = {}
        step = []
        for i in self.order():
            t = self.transitions[i]
            if not self.enabled(i, m, a, b):
                continue
            if any(residual[p] < w for p, w in t.pre.items()):
                continue
            if not self.fits_capacity(t, m, delta):
                continue
            for p, w in t.pre.items():
                residual[p] -= w
                delta[p] = delta.get(p, 0) - w
            for p, w in t.post.items():
                delta[p] = delta.get(p, 0) + w
            step.append(i)
        return step


GUARD_CHOICES = [None, None, None, "a", "not a", "b", "a and not b", "a or b"]
WEIGHTS = st.sampled_from([1, 1, 1, 2, 3])


@st.composite
def nets(draw: st.DrawFn, capacity: bool = False) -> Gen:
    """Small nets biased towards conflicts: few places, mostly weight 1, mostly no guard."""
    n = draw(st.integers(2, 4))
    tokens = tuple(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)))
    caps: tuple[int | None, ...] = (None,) * n
    if capacity:
        drawn = draw(st.lists(st.none() | st.integers(1, 4), min_size=n, max_size=n))
        caps = tuple(None if c is None else max(c, tokens[p]) for p, c in enumerate(drawn))
    place = st.integers(0, n - 1)
    arcs = st.dictionaries(place, WEIGHTS, max_size=2)
    side = st.dictionaries(place, st.integers(1, 2), max_size=1)
    transitions = []
    for _ in range(draw(st.integers(1, 6))):
        pre = draw(arcs)
        guard = draw(st.sampled_from(GUARD_CHOICES))
        if not pre and guard is None:
            guard = "a"  # the compiler refuses a transition that would fire every scan
        read = draw(side) if draw(st.integers(0, 3)) == 0 else {}
        inhibit = draw(side) if draw(st.integers(0, 3)) == 0 else {}
        transitions.append(Trans(pre, draw(st.dictionaries(place, WEIGHTS, max_size=2)), read,
                                 inhibit, draw(st.integers(0, 2)), guard))
    return Gen(tokens, caps, tuple(transitions))


@st.composite
def conservative_nets(draw: st.DrawFn) -> tuple[Gen, np.ndarray]:
    """Nets with a positive P-invariant y (y·Pre = y·Post): weighted state machines."""
    n = draw(st.integers(2, 5))
    y = [1, *draw(st.lists(st.integers(1, 2), min_size=n - 1, max_size=n - 1))]
    tokens = tuple(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)))
    place = st.integers(0, n - 1)
    transitions = []
    for _ in range(draw(st.integers(1, 6))):
        pre = draw(st.dictionaries(place, st.integers(1, 2), min_size=1, max_size=2))
        total = sum(y[p] * w for p, w in pre.items())
        target = draw(place)
        if total % y[target]:
            target = 0  # y[0] == 1 divides everything
        post = {target: total // y[target]}
        transitions.append(Trans(pre, post, draw(st.dictionaries(place, st.integers(1, 2),
                                                                  max_size=1)),
                                 draw(st.dictionaries(place, st.integers(1, 2), max_size=1)),
                                 draw(st.integers(0, 2)), draw(st.sampled_from(list(GUARDS)))))
    return Gen(tokens, (None,) * n, tuple(transitions)), np.array(y, np.int64)


inputs_strategy = st.tuples(st.booleans(), st.booleans())
input_runs = st.lists(inputs_strategy, min_size=1, max_size=8)


def one_round(gen: Gen, directory: Path, a: bool, b: bool) -> tuple[Step, np.ndarray, np.ndarray]:
    net = gen.compile(directory)
    engine = Engine(net)
    before = engine.state.marking.copy()
    step = engine.fire_round(Ctx({"a": a, "b": b}), 0)
    return step, before, engine.state.marking.copy()


def run_rounds(net: CompiledNet, runs: Sequence[tuple[bool, bool]],
               engine: Engine | None = None) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """Rounds at 0, 10, 20 ... with the given inputs; `changed` names what differs."""
    engine = engine or Engine(net)
    previous = {"a": 0, "b": 0}
    out = []
    for k, (a, b) in enumerate(runs):
        values = {"a": int(a), "b": int(b)}
        changed = [n for n in values if values[n] != previous[n]] if k else []
        step = engine.fire_round(Ctx(values, previous), k * 10, changed)
        out.append((step.fired, tuple(int(x) for x in engine.state.marking)))
        previous = values
    return out


# -- properties -----------------------------------------------------------------------------


@PROPERTY
@given(gen=nets(capacity=True), inputs=inputs_strategy)
def test_state_equation_and_no_negative_marking(io_dir: Path, gen: Gen,
                                                inputs: tuple[bool, bool]) -> None:
    step, before, after = one_round(gen, io_dir, *inputs)
    pre, post = gen.matrices()
    sigma = np.zeros(len(gen.transitions), np.int64)
    sigma[list(step.fired)] = 1  # each transition fires at most once per round
    assert len(set(step.fired)) == len(step.fired)
    assert (after >= 0).all()
    assert (after == before - pre @ sigma + post @ sigma).all()


@PROPERTY
@given(gen=nets(), inputs=inputs_strategy)
def test_step_fits_the_marking_and_is_maximal(io_dir: Path, gen: Gen,
                                              inputs: tuple[bool, bool]) -> None:
    step, before, _ = one_round(gen, io_dir, *inputs)
    pre, _ = gen.matrices()
    sigma = np.zeros(len(gen.transitions), np.int64)
    sigma[list(step.fired)] = 1
    residual = before - pre @ sigma
    assert (residual >= 0).all()  # the whole step fits M_k
    for i in range(len(gen.transitions)):
        if i in step.fired or not gen.enabled(i, before, *inputs):
            continue
        # an unselected candidate could not be added: it does not fit what is left
        assert any(residual[p] < w for p, w in gen.transitions[i].pre.items()), i


@PROPERTY
@given(gen=nets(capacity=True), inputs=inputs_strategy)
def test_step_is_priority_then_declaration_order_on_the_residual_marking(
        io_dir: Path, gen: Gen, inputs: tuple[bool, bool]) -> None:
    step, before, after = one_round(gen, io_dir, *inputs)
    assert list(step.fired) == gen.greedy(before, *inputs)
    for p, cap in enumerate(gen.capacity):
        assert cap is None or after[p] <= cap


@PROPERTY
@given(gen=nets(capacity=True), inputs=inputs_strategy)
def test_false_guard_never_fires(io_dir: Path, gen: Gen, inputs: tuple[bool, bool]) -> None:
    step, _, _ = one_round(gen, io_dir, *inputs)
    for i in step.fired:
        assert GUARDS[gen.transitions[i].guard](*inputs)


@PROPERTY
@given(gen=nets(capacity=True), inputs=inputs_strategy)
def test_marked_inhibitor_or_unmarked_test_place_never_fires(
        io_dir: Path, gen: Gen, inputs: tuple[bool, bool]) -> None:
    step, before, _ = one_round(gen, io_dir, *inputs)
    for i in step.fired:
        t = gen.transitions[i]
        assert all(before[p] < w for p, w in t.inhibit.items())  # inhibitors read M_k
        assert all(before[p] >= w for p, w in t.read.items())  # test arcs read M_k


@PROPERTY
@given(gen=nets(capacity=True), runs=input_runs)
def test_same_inputs_give_the_same_steps(io_dir: Path, gen: Gen,
                                         runs: list[tuple[bool, bool]]) -> None:
    first = run_rounds(gen.compile(io_dir), runs)
    second = run_rounds(gen.compile(io_dir), runs)  # a second compile and a second engine
    assert first == second


@PROPERTY
@given(gen=nets(capacity=True), runs=input_runs)
def test_incremental_rounds_agree_with_full_evaluation(io_dir: Path, gen: Gen,
                                                       runs: list[tuple[bool, bool]]) -> None:
    """The engine re-evaluates only what changed; a fresh engine on a copy of the state
    evaluates everything. Both must pick the same step every round (transitions without an
    input place included)."""
    net = gen.compile(io_dir)
    engine = Engine(net)
    previous = {"a": 0, "b": 0}
    for k, (a, b) in enumerate(runs):
        values = {"a": int(a), "b": int(b)}
        fresh = Engine(net, engine.state.copy()).fire_round(Ctx(values, previous), k * 10)
        changed = [n for n in values if values[n] != previous[n]] if k else []
        step = engine.fire_round(Ctx(values, previous), k * 10, changed)
        assert step.fired == fresh.fired, k
        previous = values


@PROPERTY
@given(gen=nets(capacity=True), runs=input_runs, data=st.data())
def test_a_primed_engine_adopting_another_marking_runs_as_a_fresh_one(
        io_dir: Path, gen: Gen, runs: list[tuple[bool, bool]], data: st.DataObject) -> None:
    """Engine.prime() (an online change, off the scan) looks at the initial marking; the
    swap then hands it another marking and enabling timers. Every round after must be the
    one an engine that never primed gives: steps, markings and timers."""
    net = gen.compile(io_dir)
    primed = Engine(net)
    primed.prime()
    n = len(gen.tokens)
    marking = np.array(data.draw(st.lists(st.integers(0, 3), min_size=n, max_size=n)),
                       dtype=np.int64)
    state = primed.state.copy()
    state.marking[:] = marking
    state.enabled_since = data.draw(st.dictionaries(
        st.integers(0, len(gen.transitions) - 1), st.integers(-50, 0), max_size=3))
    plain = Engine(net, state.copy())
    primed.state = state
    primed.invalidate()
    previous = {"a": 0, "b": 0}
    for k, (a, b) in enumerate(runs):
        values = {"a": int(a), "b": int(b)}
        changed = [name for name in values if values[name] != previous[name]] if k else []
        ours = primed.fire_round(Ctx(values, previous), k * 10, changed)
        theirs = plain.fire_round(Ctx(values, previous), k * 10, changed)
        assert ours.fired == theirs.fired, k
        assert primed.state.marking.tolist() == plain.state.marking.tolist(), k
        assert primed.state.enabled_since == plain.state.enabled_since, k
        previous = values


def test_a_primed_engine_keeps_carried_timers_and_starts_new_ones_at_the_swap(
        tmp_path: Path) -> None:
    """An online change carries enabling timers by transition name. After prime(), a timed
    transition enabled before and after the swap keeps its carried start; one enabled only
    now starts at the swap scan; a carried timer of a transition no longer enabled goes."""
    net = compile_program(tmp_path, """places:
  a: {tokens: 1}
  b: {tokens: 1}
  c: {tokens: 0}
  d: {}
transitions:
  slow_a: {from: [a], to: [d], delay: 50ms}
  slow_b: {from: [b], to: [d], delay: 50ms}
  slow_c: {from: [c], to: [d], delay: 50ms}
""")
    primed = Engine(net)
    primed.prime()
    state = primed.state.copy()
    index = {t.name: t.index for t in net.transitions}
    state.enabled_since = {index["slow_a"]: 1_000_000, index["slow_c"]: 2_000_000}
    plain = Engine(net, state.copy())
    primed.state = state
    primed.invalidate()
    now = 10_000_000
    assert primed.fire_round(Ctx(), now).fired == plain.fire_round(Ctx(), now).fired == ()
    expected = {index["slow_a"]: 1_000_000, index["slow_b"]: now}
    assert primed.state.enabled_since == plain.state.enabled_since == expected


@PROPERTY
@given(gen=nets(capacity=True), runs=input_runs)
def test_scan_does_not_mutate_its_input_image(io_dir: Path, gen: Gen,
                                              runs: list[tuple[bool, bool]]) -> None:
    bench = Bench(gen.compile(io_dir))
    for k, (a, b) in enumerate(runs, 1):
        bench.set(a=a, b=b, w=k)
        before = bench.inputs.copy()
        bench.scan(k * 10_000_000)
        assert bench.inputs.equals(before)
        assert (bench.plc.image.ix == before.ix).all()  # latched as given


@PROPERTY
@given(data=conservative_nets(), runs=input_runs)
def test_p_invariant_is_preserved(io_dir: Path, data: tuple[Gen, np.ndarray],
                                  runs: list[tuple[bool, bool]]) -> None:
    gen, y = data
    net = gen.compile(io_dir)
    engine = Engine(net)
    pre, post = gen.matrices()
    assert (y @ pre == y @ post).all()  # the generator's claim
    weight = int(y @ engine.state.marking)
    for _, marking in run_rounds(net, runs, engine):
        assert int(y @ np.array(marking)) == weight


# -- unit tests: conflicts, arcs, capacity --------------------------------------------------


def fired_names(net: CompiledNet, step: Step) -> list[str]:
    return [net.transitions[i].name for i in step.fired]


def test_priority_decides_a_conflict_then_declaration_order(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  q: {tokens: 1}
  x: {}
transitions:
  low:    {from: [p], to: [x], priority: 0}
  high:   {from: [p], to: [x], priority: 1}
  first:  {from: [q], to: [x]}
  second: {from: [q], to: [x]}
""")
    step = Engine(net).fire_round(Ctx(), 0)
    assert fired_names(net, step) == ["high", "first"]  # step order: priority, then declaration


def test_residual_marking_lets_a_lower_priority_transition_take_what_is_left(
        tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 2}
  x: {}
transitions:
  one: {from: [p], to: [x], priority: 3}
  two: {from: {p: 2}, to: [x], priority: 2}
  three: {from: [p], to: [x], priority: 1}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert fired_names(net, step) == ["one", "three"]  # `two` does not fit the residual 1
    assert engine.state.marking_by_name(net) == {"x": 2}


def test_test_arc_reads_the_round_start_marking_and_does_not_consume(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  q: {tokens: 2}
  x: {}
  y: {}
transitions:
  take: {from: [p], to: [x], priority: 1}
  look: {read: [p], from: [q], to: [y]}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert fired_names(net, step) == ["take", "look"]  # p was marked in M_k
    assert engine.state.marking_by_name(net) == {"q": 1, "x": 1, "y": 1}
    assert fired_names(net, engine.fire_round(Ctx(), 10)) == []  # p is empty now


def test_test_arc_weight_and_repeated_reads(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 2}
  q: {tokens: 3}
  y: {}
transitions:
  look: {read: {p: 2}, from: [q], to: [y]}
""")
    engine = Engine(net)
    for k in range(3):
        engine.fire_round(Ctx(), k)
    assert engine.state.marking_by_name(net) == {"p": 2, "y": 3}


def test_inhibitor_arc_reads_the_round_start_marking(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  x: {}
  r: {tokens: 1}
  y: {}
transitions:
  fill: {from: [p], to: [x], priority: 1}
  unless_x: {inhibit: [x], from: [r], to: [y]}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert fired_names(net, step) == ["fill", "unless_x"]  # x was empty in M_k


def test_inhibitor_weight_is_a_threshold(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  x: {tokens: 1}
  r: {tokens: 2}
  y: {}
transitions:
  below_two: {inhibit: {x: 2}, from: [r], to: [y, x]}
""")
    engine = Engine(net)
    assert fired_names(net, engine.fire_round(Ctx(), 0)) == ["below_two"]
    assert fired_names(net, engine.fire_round(Ctx(), 1)) == []  # x holds 2 now
    assert engine.state.marking_by_name(net) == {"x": 2, "r": 1, "y": 1}


def test_capacity_blocks_until_there_is_room(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  src: {tokens: 3}
  buf: {tokens: 1, capacity: 2}
  out: {}
transitions:
  put_a: {from: [src], to: [buf], priority: 2}
  put_b: {from: [src], to: [buf], priority: 1}
  drain: {from: [buf], to: [out], when: a}
""")
    engine = Engine(net)
    assert fired_names(net, engine.fire_round(Ctx(), 0)) == ["put_a"]  # only one fits
    assert fired_names(net, engine.fire_round(Ctx(), 1)) == []  # buf is full
    assert engine.state.marking_by_name(net) == {"src": 2, "buf": 2}
    step = engine.fire_round(Ctx({"a": 1}), 2, ["a"])
    # drain is taken after both puts in step order, so its room is not yet there for them
    assert fired_names(net, step) == ["drain"]
    assert fired_names(net, engine.fire_round(Ctx(), 3, ["a"])) == ["put_a"]


def test_capacity_counts_what_the_transition_itself_consumes(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  buf: {tokens: 2, capacity: 2}
  n: {tokens: 1}
transitions:
  cycle: {from: [buf, n], to: [buf]}
""")
    engine = Engine(net)
    assert fired_names(net, engine.fire_round(Ctx(), 0)) == ["cycle"]
    assert engine.state.marking_by_name(net) == {"buf": 2}


# -- timing ---------------------------------------------------------------------------------

DELAY = """
places:
  p: {tokens: 1}
  x: {}
transitions:
  t: {from: [p], to: [x], when: a, delay: 30ns}
"""


def drive(net: CompiledNet, schedule: Sequence[tuple[int, int]], engine: Engine | None = None
          ) -> dict[int, list[str]]:
    """Rounds at the given times with the given value of `a`; what fired when."""
    engine = engine or Engine(net)
    previous = 0
    fired = {}
    for now, a in schedule:
        step = engine.fire_round(Ctx({"a": a}, {"a": previous}), now,
                                 ["a"] if a != previous else [])
        fired[now] = fired_names(net, step)
        previous = a
    return fired


def test_enabling_delay_fires_once_enabled_for_d(tmp_path: Path) -> None:
    net = compile_program(tmp_path, DELAY)
    fired = drive(net, [(0, 0), (10, 1), (20, 1), (30, 1), (40, 1), (50, 1)])
    assert [t for t, f in fired.items() if f] == [40]  # enabled at 10, fires at 10 + 30


def test_enabling_delay_restarts_when_disabled(tmp_path: Path) -> None:
    net = compile_program(tmp_path, DELAY)
    fired = drive(net, [(0, 0), (10, 1), (20, 1), (30, 0), (40, 1), (50, 1), (60, 1), (70, 1),
                        (80, 1)])
    assert [t for t, f in fired.items() if f] == [70]  # re-enabled at 40


def test_enabling_delay_latency_is_between_d_and_d_plus_one_period(tmp_path: Path) -> None:
    net = compile_program(tmp_path, DELAY)  # d = 30 ns, period 7 ns
    times = list(range(0, 120, 7))
    fired = drive(net, [(t, 1 if t >= 7 else 0) for t in times])
    (when,) = [t for t, f in fired.items() if f]
    assert 30 <= when - 7 < 30 + 7


DURATION = """
places:
  p: {tokens: 2}
  x: {}
transitions:
  work: {from: [p], to: [x], duration: 25ns, outputs: [r], do: [set m]}
"""


def test_three_phase_firing_consumes_at_start_and_produces_at_the_end(tmp_path: Path) -> None:
    net = compile_program(tmp_path, DURATION)
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert fired_names(net, step) == ["work"]
    assert ("m", 1) in step.writes and ("r", 1) in step.writes  # actions at start, busy on
    assert engine.state.marking_by_name(net) == {"p": 1}  # consumed, nothing produced yet
    for now in (10, 20):
        step = engine.fire_round(Ctx(), now)
        assert step.fired == () and step.completed == ()  # single server: p waits
    step = engine.fire_round(Ctx(), 30)  # first round at or after 0 + 25
    assert [net.transitions[i].name for i in step.completed] == ["work"]
    assert step.fired == ()
    assert ("r", 0) in step.writes  # the busy output drops at the end
    assert engine.state.marking_by_name(net) == {"p": 1, "x": 1}
    step = engine.fire_round(Ctx(), 40)  # the next firing starts the round after
    assert fired_names(net, step) == ["work"]
    assert engine.state.marking_by_name(net) == {"x": 1}


def test_three_phase_outputs_are_on_while_busy_through_the_scan(tmp_path: Path) -> None:
    net = compile_program(tmp_path, DURATION)
    bench = Bench(net)  # starts at 0: `work` fires in the first scan
    seen = []
    for now in range(10, 100, 10):
        bench.scan(now)
        seen.append((now, bench.get("r"), bench.marking().get("x", 0)))
    assert seen[:2] == [(10, 1, 0), (20, 1, 0)]
    assert seen[2] == (30, 0, 1)  # produced at 30: latency between d and d + one period
    assert seen[3] == (40, 1, 1)  # second firing
    assert seen[6] == (70, 0, 2)


# -- outputs --------------------------------------------------------------------------------


def test_moore_outputs_follow_the_marking(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  idle: {tokens: 1, outputs: [r]}
  busy: {outputs: {qw: 42, m: true}}
transitions:
  go: {from: [idle], to: [busy], when: a}
  back: {from: [busy], to: [idle], when: "not a"}
""")
    bench = Bench(net)
    assert (bench.get("r"), bench.get("qw"), bench.get("m")) == (1, 0, 0)
    bench.set(a=1)
    bench.scan(10)
    assert (bench.get("r"), bench.get("qw"), bench.get("m")) == (0, 42, 1)
    bench.set(a=0)
    bench.scan(20)
    assert (bench.get("r"), bench.get("qw"), bench.get("m")) == (1, 0, 0)


def test_mealy_action_after_moore_last_writer_wins(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  idle: {tokens: 1}
  busy: {outputs: {r: true, qw: 5}}
transitions:
  go: {from: [idle], to: [busy], when: a, do: [reset r, "qw = 9"]}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx({"a": 1}), 0)
    # Moore values of M_{k+1} first, then the actions in step order
    assert step.writes == (("qw", 5), ("r", 1), ("r", 0), ("qw", 9))
    bench = Bench(net)
    bench.set(a=1)
    bench.scan(10)
    assert (bench.get("r"), bench.get("qw")) == (0, 9)


def test_actions_in_step_order_last_writer_wins(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  q: {tokens: 1}
transitions:
  later: {from: [q], do: ["qw = 2", set r]}
  sooner: {from: [p], priority: 1, do: ["qw = 1", reset r]}
""")
    bench = Bench(net)
    assert bench.last.fired == ("sooner", "later")
    assert (bench.get("qw"), bench.get("r")) == (2, 1)


def test_write_actions_never_wrap_words_and_take_truth_of_bools(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
transitions:
  t: {from: [p], do: ["qw = 0 - 1", "mw = 65536 + 3", "m = 5", "r = w > 3"]}
""")
    bench = Bench(net, start=False)
    bench.set(w=4)
    bench.scan(0, [START])
    # Out of a word's range: a diagnostic, the write not done (qw keeps its safe 7), never
    # wrapped (issue 30).
    assert (bench.get("qw"), bench.get("mw"), bench.get("m"), bench.get("r")) == (7, 0, 1, 1)
    assert bench.plc.engine is not None
    found = bench.plc.engine.diagnostics
    assert any("qw = '0 - 1' failed (-1 is out of range of word (0..65535))" in d for d in found)
    assert any("mw = '65536 + 3' failed (65539 is out of range of word" in d for d in found)


def test_pulse_lasts_one_scan(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 2}
transitions:
  t: {from: [p], when: "rising(a)", do: [pulse r]}
""")
    bench = Bench(net)
    values = []
    for now, a in ((10, 1), (20, 1), (30, 1), (40, 0), (50, 1), (60, 1)):
        bench.set(a=a)
        bench.scan(now)
        values.append(bench.get("r"))
    assert values == [1, 0, 0, 0, 1, 0]


def test_a_failing_action_writes_nothing_and_is_diagnosed(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
transitions:
  t: {from: [p], do: ["qw = w * 9223372036854775807 * 2"]}
""")
    bench = Bench(net, start=False)
    bench.set(w=3)
    bench.scan(0, [START])
    assert bench.last.fired == ("t",)
    assert bench.get("qw") == 7  # the safe value written while STOPPED stays
    assert bench.plc.engine is not None
    assert "t: qw = " in bench.plc.engine.diagnostics[0]


# -- coloured tokens ------------------------------------------------------------------------

COLOURED = """
places:
  parts: {tokens: [{id: 1, weight: 5}, {id: 2, weight: 12}, {id: 3, weight: 20}]}
  heavy: {coloured: true}
transitions:
  sort:
    from: [{place: parts, var: x}]
    to: [{place: heavy, token: {id: "x.id", kg: "x.weight * 2", tag: "'H'", checked: "a"}}]
    when: "x.weight > 10"
    do: ["qw = x.id"]
"""


def test_coloured_binding_picks_a_token_the_guard_accepts(tmp_path: Path) -> None:
    net = compile_program(tmp_path, COLOURED)
    engine = Engine(net)
    step = engine.fire_round(Ctx({"a": 1}), 0)
    assert fired_names(net, step) == ["sort"]
    assert ("qw", 2) in step.writes  # actions see the bound token
    tokens = engine.state.tokens
    assert tokens[net.place_index["parts"]] == [{"id": 1, "weight": 5}, {"id": 3, "weight": 20}]
    assert tokens[net.place_index["heavy"]] == [{"id": 2, "kg": 24, "tag": "H", "checked": True}]
    engine.fire_round(Ctx({"a": 1}), 1)
    assert engine.fire_round(Ctx({"a": 1}), 2).fired == ()  # only id 1 (5 kg) is left
    assert engine.state.marking_by_name(net) == {"parts": 1, "heavy": 2}


def test_coloured_pass_through_and_fifo_order(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  queue: {tokens: [{n: 1}, {n: 2}]}
  done: {coloured: true}
  plain: {}
transitions:
  move: {from: [{place: queue, var: t}], to: [{place: done, token: t}, plain], when: a}
""")
    engine = Engine(net)
    engine.fire_round(Ctx({"a": 1}), 0)
    assert engine.state.tokens[net.place_index["done"]] == [{"n": 1}]  # oldest first
    engine.fire_round(Ctx({"a": 1}), 1)
    assert engine.state.tokens[net.place_index["done"]] == [{"n": 1}, {"n": 2}]
    assert engine.state.marking_by_name(net) == {"done": 2, "plain": 2}


def test_coloured_counter_as_in_the_example_programs(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  count: {tokens: [{n: 0}]}
  ready: {tokens: 3}
transitions:
  tick:
    from: [ready, {place: count, var: c}]
    to: [{place: count, token: {n: "c.n + 1"}}]
    do: ["mw = c.n + 1"]
""")
    bench = Bench(net)
    for now in (10, 20, 30):
        bench.scan(now)
    assert bench.get("mw") == 3
    assert bench.plc.engine is not None
    assert bench.plc.engine.state.tokens[net.place_index["count"]] == [{"n": 3}]


# -- interleaving API -----------------------------------------------------------------------


def test_interleaving_enabled_transitions_and_fire_one(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  x: {}
  y: {}
transitions:
  left:  {from: [p], to: [x]}
  right: {from: [p], to: [y], priority: 1}
  guarded: {from: [p], to: [y], when: a}
""")
    state = NetState.initial(net)
    assert enabled_transitions(net, state, Ctx()) == ["right", "left"]  # all, in order
    assert enabled_transitions(net, state, Ctx({"a": 1})) == ["right", "left", "guarded"]
    after = fire_one(net, state, "left", Ctx())
    assert after.marking_by_name(net) == {"x": 1}
    assert state.marking_by_name(net) == {"p": 1}  # the given state is not modified
    assert enabled_transitions(net, after, Ctx()) == []
    with pytest.raises(ValueError, match="transition 'guarded' is not enabled"):
        fire_one(net, state, "guarded", Ctx())


# -- bugs found (expected to fail until fixed) -----------------------------------------------


def test_source_transition_fires_every_round_while_its_guard_holds(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  parts: {}
transitions:
  arrive: {to: [parts], when: a}
""")
    engine = Engine(net)
    engine.fire_round(Ctx({"a": 1}), 0)
    for k in range(1, 4):
        engine.fire_round(Ctx({"a": 1}, {"a": 1}), k)
    assert engine.state.marking_by_name(net) == {"parts": 4}


def test_repeated_input_arc_counts_as_weight(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  x: {}
transitions:
  t: {from: [p, p], to: [x]}
""")
    engine = Engine(net)
    assert engine.fire_round(Ctx(), 0).fired == ()
    assert (engine.state.marking >= 0).all()


def test_repeated_output_arc_respects_capacity(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  x: {capacity: 1}
transitions:
  t: {from: [p], to: [x, x]}
""")
    engine = Engine(net)
    engine.fire_round(Ctx(), 0)
    assert engine.state.marking_by_name(net).get("x", 0) <= 1


def test_capacity_holds_with_a_three_phase_firing_in_progress(tmp_path: Path) -> None:
    """A three-phase firing's production is reserved from its start: `fast` may not fill the
    place `slow` will produce into (once a known bug: the completion overfilled it)."""
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  q: {tokens: 1}
  x: {capacity: 1}
transitions:
  slow: {from: [p], to: [x], duration: 15ns}
  fast: {from: [q], to: [x], when: a}
""")
    engine = Engine(net)
    for now, a in ((0, 0), (10, 1), (20, 1), (30, 1)):
        engine.fire_round(Ctx({"a": a}), now, ["a"] if now == 10 else [])
        assert engine.state.marking_by_name(net).get("x", 0) <= 1, now


def test_the_reserved_room_is_free_again_once_the_three_phase_firing_has_produced(
        tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  q: {tokens: 1}
  x: {capacity: 1}
  y: {}
transitions:
  slow: {from: [p], to: [x], duration: 15ns}
  fast: {from: [q], to: [x], when: a}
  out: {from: [x], to: [y], when: b}
""")
    engine = Engine(net)
    fired = []
    previous = {"a": 0, "b": 0}
    for now, a, b in ((0, 0, 0), (10, 1, 0), (20, 1, 0), (30, 1, 1), (40, 1, 0)):
        values = {"a": a, "b": b}
        changed = [n for n in values if values[n] != previous[n]]
        fired.append(fired_names(net, engine.fire_round(Ctx(values, previous), now, changed)))
        assert engine.state.marking_by_name(net).get("x", 0) <= 1, now
        previous = values
    assert fired == [["slow"], [], [], ["out"], ["fast"]]
    assert engine.state.marking_by_name(net) == {"x": 1, "y": 1}


def test_a_reservation_restarts_the_enabling_delay_of_a_transition_it_blocks(
        tmp_path: Path) -> None:
    """`fast` is enabled at 0; `slow` starting its duration fills x's room at once, so `fast`
    is disabled from then on and its delay starts over when room is made (at 20, seen at 30),
    as a fresh evaluation of every round would have it."""
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  q: {tokens: 1}
  x: {tokens: 1, capacity: 2}
  y: {}
transitions:
  slow: {from: [p], to: [x], duration: 20ns, priority: 1}
  fast: {from: [q], to: [x], delay: 25ns}
  out: {from: [x], to: [y], when: b}
""")
    engine = Engine(net)
    fired = []
    previous = {"b": 0}
    for now in range(0, 70, 10):
        values = {"b": int(now == 20)}
        changed = [n for n in values if values[n] != previous[n]]
        fired.append(fired_names(net, engine.fire_round(Ctx(values, previous), now, changed)))
        previous = values
    assert fired == [["slow"], [], ["out"], [], [], [], ["fast"]]


def test_two_coloured_transitions_take_different_tokens_in_one_round(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  parts: {tokens: [{id: 1}, {id: 2}]}
  left: {coloured: true}
  right: {coloured: true}
transitions:
  pick_two: {from: [{place: parts, var: k}], to: [{place: left, token: k}],
             when: "k.id == 2", priority: 1}
  pick_any: {from: [{place: parts, var: k}], to: [{place: right, token: k}]}
""")
    engine = Engine(net)
    step = engine.fire_round(Ctx(), 0)
    assert fired_names(net, step) == ["pick_two", "pick_any"]
    tokens = engine.state.tokens
    assert tokens[net.place_index["left"]] == [{"id": 2}]
    assert tokens[net.place_index["right"]] == [{"id": 1}]


def test_a_token_a_higher_priority_transition_bound_is_not_bound_again(tmp_path: Path) -> None:
    """Issue 43: both transitions would bind the oldest part (no guard picks another); the
    first one's binding reserves it, so the second takes the next part: no token is
    consumed twice in one round."""
    net = compile_program(tmp_path, """
places:
  parts: {tokens: [{id: 1}, {id: 2}]}
  left: {coloured: true}
  right: {coloured: true}
transitions:
  pick_first: {from: [{place: parts, var: k}], to: [{place: left, token: k}], priority: 1}
  pick_any: {from: [{place: parts, var: k}], to: [{place: right, token: k}]}
""")
    engine = Engine(net)
    assert fired_names(net, engine.fire_round(Ctx(), 0)) == ["pick_first", "pick_any"]
    tokens, at = engine.state.tokens, net.place_index
    assert (tokens[at["left"]], tokens[at["right"]]) == ([{"id": 1}], [{"id": 2}])
    assert tokens.get(at["parts"], []) == []


def test_a_plain_arc_from_a_coloured_place_reserves_the_oldest_free_token(tmp_path: Path) -> None:
    """A coloured transition with a plain arc from a coloured place takes its oldest free
    token: a lower-priority transition binding from that place gets the next one."""
    net = compile_program(tmp_path, """
places:
  parts: {tokens: [{id: 1}]}
  lids: {tokens: [{id: 10}, {id: 20}]}
  done: {coloured: true}
  spare: {coloured: true}
transitions:
  close: {from: [{place: parts, var: k}, lids], to: [{place: done, token: k}], priority: 1}
  grab: {from: [{place: lids, var: l}], to: [{place: spare, token: l}]}
""")
    engine = Engine(net)
    assert fired_names(net, engine.fire_round(Ctx(), 0)) == ["close", "grab"]
    tokens, at = engine.state.tokens, net.place_index
    assert (tokens[at["done"]], tokens[at["spare"]]) == ([{"id": 1}], [{"id": 20}])
    assert tokens.get(at["lids"], []) == []


def test_guard_on_a_bit_the_program_sets_fires(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  p: {tokens: 1}
  x: {}
  z: {tokens: 1}
  y: {}
transitions:
  t: {from: [p], to: [x], when: a, do: [set m]}
  u: {from: [z], to: [y], when: m}
""")
    bench = Bench(net)
    bench.set(a=1)
    for now in (10, 20, 30):
        bench.scan(now)
    assert bench.marking() == {"x": 1, "y": 1}


MOORE_HELD = """
places:
  on: {tokens: 1, outputs: {r: true, m: true}}
  p: {tokens: 1}
transitions:
  once: {from: [p], do: [reset r]}
  never: {from: [on], when: "false"}
"""


MOORE_PLAIN = MOORE_HELD.replace("  once: {from: [p], do: [reset r]}\n", "")


def test_moore_output_is_reasserted_over_an_hmi_write(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, MOORE_PLAIN))
    bench.scan(10)
    assert bench.get("r") == 1
    bench.scan(20, hmi=[HmiWrite(parse_address("%QX0.1"), (0,))])
    assert bench.get("r") == 1  # "output on while marked": the program's output


def test_moore_memory_output_is_reasserted_over_an_hmi_write(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, MOORE_PLAIN))
    assert bench.get("m") == 1
    bench.scan(10, hmi=[HmiWrite(parse_address("%MX0.0"), (0,))])
    bench.scan(20)
    assert bench.get("m") == 1


def test_moore_output_comes_back_the_round_after_an_action_overrode_it(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, MOORE_HELD))
    assert bench.last.fired == ("once",)
    assert bench.get("r") == 0  # the action is the last writer of its round
    bench.scan(10)
    assert bench.get("r") == 1  # next round: outputs from the marking, `on` is marked


# -- plain paths against the general path ----------------------------------------------------


@dataclass(frozen=True)
class Extra:
    """What makes a transition leave the plain paths: a delay, a duration, actions."""

    delay_ns: int
    duration_ns: int
    do: tuple[str, ...]


EXTRA_GUARDS = ["rising(a)", "falling(b)", "w > 1"]
ACTIONS = st.sampled_from(["set m", "reset m", "pulse r", "qw = w + 1", "set q"])


@st.composite
def mixed_nets(draw: st.DrawFn) -> str:
    """Program text of a random net mixing plain transitions with timed, guarded, capped,
    acting ones and places driving outputs: each kind takes its own path in one round."""
    gen = draw(nets(capacity=draw(st.booleans())))
    # nets() puts an inhibitor on most transitions with a test arc: drop some, so that test
    # arcs also meet the inline enabling check of arcs-only transitions.
    gen = replace(gen, transitions=tuple(replace(t, inhibit={}) if draw(st.booleans()) else t
                                         for t in gen.transitions))
    extras = [Extra(draw(st.sampled_from([0, 0, 0, 10, 25])),
                    draw(st.sampled_from([0, 0, 0, 15])),
                    tuple(draw(st.lists(ACTIONS, max_size=2))) if draw(st.booleans()) else ())
              for _ in gen.transitions]
    guards = {i: draw(st.sampled_from(EXTRA_GUARDS)) for i, t in enumerate(gen.transitions)
              if t.pre and t.guard is None and draw(st.integers(0, 4)) == 1}
    driving = draw(st.sets(st.integers(0, len(gen.tokens) - 1), max_size=2))
    lines = []
    for line in gen.text().splitlines():
        place = line.strip().split(":")[0]
        if line.startswith("  p") and int(place[1:]) in driving:
            line = line[:-1] + ", outputs: [q]}"
        lines.append(line)
        if line.startswith("  t") and line.endswith(":"):
            i = int(line.strip()[1:-1])
            lines += _extra_lines(extras[i], guards.get(i))
    return "\n".join(lines) + "\n"


def _extra_lines(extra: Extra, guard: str | None) -> list[str]:
    out = [f"    delay: {extra.delay_ns}ns"] if extra.delay_ns else []
    out += [f"    duration: {extra.duration_ns}ns"] if extra.duration_ns else []
    out += [f"    do: [{', '.join(extra.do)}]"] if extra.do else []
    return out + ([f'    when: "{guard}"'] if guard is not None else [])


word_runs = st.lists(st.tuples(st.booleans(), st.booleans(), st.integers(0, 3)),
                     min_size=1, max_size=10)


def observed(engine: Engine) -> tuple[object, ...]:
    """Everything a round leaves behind, enabled_since in insertion order included."""
    st_ = engine.state
    return (tuple(int(x) for x in st_.marking), list(st_.enabled_since.items()),
            {t: (b.end_ns, b.produce) for t, b in st_.busy.items()}, st_.tokens,
            list(engine.diagnostics))


@settings(PROPERTY, max_examples=200)  # many kinds of transition to mix: more examples
@given(text=mixed_nets(), runs=word_runs)
def test_plain_paths_fire_the_same_rounds_as_the_general_path(
        io_dir: Path, text: str, runs: list[tuple[bool, bool, int]]) -> None:
    net = compile_text("io_image: io.yaml\n" + text, str(io_dir / "mixed.yaml"))
    fast, general = Engine(net), Engine(net, plain_paths=False)
    assert observed(fast) == observed(general)
    previous = {"a": 0, "b": 0, "w": 0}
    for k, (a, b, w) in enumerate(runs):
        values = {"a": int(a), "b": int(b), "w": w}
        changed = [n for n in values if values[n] != previous[n]] if k else []
        steps = [e.fire_round(Ctx(values, previous), k * 10, changed) for e in (fast, general)]
        assert steps[0] == steps[1], k
        assert observed(fast) == observed(general), k
        previous = values


@PROPERTY
@given(text=mixed_nets(), runs=word_runs)
def test_engine_follows_a_marking_written_from_outside(
        io_dir: Path, text: str, runs: list[tuple[bool, bool, int]]) -> None:
    """A restore puts a new NetState (or new counts) under a running engine, then calls
    invalidate(): the next rounds are those of a fresh engine on that state."""
    net = compile_text("io_image: io.yaml\n" + text, str(io_dir / "mixed.yaml"))
    engine = Engine(net)
    previous = {"a": 0, "b": 0, "w": 0}
    for k, (a, b, w) in enumerate(runs):
        values = {"a": int(a), "b": int(b), "w": w}
        if k % 3 == 1:
            state = engine.state.copy()
            state.marking[:] = net.initial
            engine.state = state
            engine.invalidate()
        elif k % 3 == 2:
            engine.state.marking[0] += 1  # in place: the same array
            engine.invalidate()
        fresh = Engine(net, engine.state.copy())
        step = engine.fire_round(Ctx(values, previous), k * 10, list(values))
        assert step.fired == fresh.fire_round(Ctx(values, previous), k * 10,
                                              list(values)).fired, k
        assert observed(engine)[0] == observed(fresh)[0], k
        assert engine.state.enabled_since == fresh.state.enabled_since, k
        previous = values


# -- run-time diagnostics: located, counted, the first 100 kept (issue 43) --------------------

def _failing_guards(tmp_path: Path, count: int) -> CompiledNet:
    return compile_program(tmp_path, "places:\n  p: {tokens: 1}\ntransitions:\n" + "".join(
        f'  t{n}: {{from: [p], when: "mw // w > 1"}}\n' for n in range(count)))


def test_a_guard_that_raises_is_false_located_and_counted_with_its_scan(tmp_path: Path) -> None:
    net = _failing_guards(tmp_path, 2)
    engine = Engine(net)
    assert (engine.diagnostics, engine.diagnostic_count) == ([], 0)
    engine.scan = 7
    assert engine.scan == 7
    step = engine.fire_round(Ctx({"mw": 4, "w": 0}), 0)
    assert step.fired == ()  # taken as false: p keeps its token
    assert engine.state.marking_by_name(net) == {"p": 1}
    path = tmp_path / "prog.yaml"
    assert engine.diagnostics == [
        f"scan 7: {path}:{line}: transition t{n}: guard 'mw // w > 1' failed (integer division "
        "by zero); taken as false" for n, line in ((0, 6), (1, 7))]
    assert engine.diagnostic_count == 2


def test_the_first_100_diagnostics_are_kept_and_every_one_counted(tmp_path: Path) -> None:
    for count in (100, 101):  # MAX_DIAGNOSTICS exactly, and one over
        (tmp_path / str(count)).mkdir()
        engine = Engine(_failing_guards(tmp_path / str(count), count))
        engine.fire_round(Ctx({"mw": 4, "w": 0}), 0)
        assert len(engine.diagnostics) == 100, count
        assert engine.diagnostic_count == count
        assert engine.diagnostics[-1].startswith("scan 0: ") and " transition t99: " in \
            engine.diagnostics[-1]


# -- edges the engine's fast tests did not sit on (issue 43) ----------------------------------

@pytest.mark.parametrize("bound", ["capacity", "coloured"])
def test_an_inhibitor_at_exactly_its_weight_blocks_a_capped_or_coloured_transition(
        tmp_path: Path, bound: str) -> None:
    src = "{tokens: [{n: 1}, {n: 2}]}" if bound == "coloured" else "{tokens: 2}"
    arc = "{place: r, var: v}" if bound == "coloured" else "r"
    net = compile_program(tmp_path, f"""
places:
  x: {{tokens: 1}}
  r: {src}
  y: {{capacity: 5}}
transitions:
  below_two: {{inhibit: {{x: 2}}, from: [{arc}], to: [y, x]}}
""")
    engine = Engine(net)
    assert fired_names(net, engine.fire_round(Ctx(), 0)) == ["below_two"]  # x held 1
    assert fired_names(net, engine.fire_round(Ctx(), 1)) == []  # x holds 2: blocked
    assert engine.state.marking_by_name(net) == {"x": 2, "r": 1, "y": 1}


def test_a_timed_source_fires_again_each_time_it_completes(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
places:
  x: {}
transitions:
  make: {to: [x], duration: 10ns}
""")
    engine = Engine(net)
    fired = [fired_names(net, engine.fire_round(Ctx(), now)) for now in range(0, 50, 5)]
    # completes at 10, 25, 40; starts again the round after each
    assert fired == [["make"], [], [], ["make"], [], [], ["make"], [], [], ["make"]]
    assert engine.state.marking_by_name(net) == {"x": 3}


@pytest.mark.parametrize("marked", [True, False])
def test_an_output_pulsed_and_driven_by_a_place_follows_the_place_after_the_pulse(
        tmp_path: Path, marked: bool) -> None:
    net = compile_program(tmp_path, f"""
places:
  s: {{tokens: 1}}
  on: {{outputs: [r]}}
  off: {{}}
transitions:
  t: {{from: [s], to: [{'on' if marked else 'off'}], do: [pulse r]}}
""")
    bench = Bench(net)  # t fires in the first scan: r pulsed; `on` drives r when marked
    values = [bench.get("r")]
    for now in (10, 20):
        bench.scan(now)
        values.append(bench.get("r"))
    assert values == [1, 1, 1] if marked else [1, 0, 0]  # the marking decides after the pulse


def test_a_timed_coloured_completion_is_held_to_the_coloured_place_limit(tmp_path: Path) -> None:
    net = compile_program(tmp_path, """
limits: {coloured_place: 2}
places:
  a: {tokens: [{n: 1}]}
  b: {tokens: [{n: 2}, {n: 3}]}
  out: {coloured: true}
transitions:
  move: {from: [{place: a, var: v}], to: [{place: out, token: v}], duration: 10ns}
  fill: {from: [{place: b, var: v}], to: [{place: out, token: v}]}
""")
    engine = Engine(net)  # move's record is not in `out` while it is busy; fill fills `out`
    engine.fire_round(Ctx(), 0)
    engine.fire_round(Ctx(), 5)
    assert engine.state.tokens[net.place_index["out"]] == [{"n": 2}, {"n": 3}]
    with pytest.raises(PlcFault) as err:
        engine.fire_round(Ctx(), 10)
    assert err.value.reason == ("place out: 3 coloured tokens exceed the limit 2 "
                                "(limits.coloured_place; transition move completing)")


def test_an_engine_runs_a_state_whose_marking_is_a_plain_list(tmp_path: Path) -> None:
    """core/engine/live.py's fallback: a marking that is not a buffer is used as it is."""
    net = compile_program(tmp_path, """
places:
  p: {tokens: 2}
  q: {}
transitions:
  t: {from: [p], to: [q]}
""")
    engine = Engine(net)
    state = NetState.initial(net)
    engine.state = replace(state, marking=[int(n) for n in state.marking])  # type: ignore[arg-type]
    engine.invalidate()
    assert [engine.fire_round(Ctx(), n).fired for n in range(3)] == [(0,), (0,), ()]
    assert engine.state.marking == [0, 2]


def test_a_diagnostic_that_names_no_transition_is_kept_unlocated(tmp_path: Path) -> None:
    from softplc.core.engine.diagnostics import Diagnostics
    diag = Diagnostics(_failing_guards(tmp_path, 1))
    diag.report("output r = 5 failed (out of range)")  # outputs.py's, no transition's name
    diag.report("t0: qw = 'x' failed (text)")
    assert diag.messages == ["scan 0: transition output r = 5 failed (out of range)",
                             f"scan 0: {tmp_path / 'prog.yaml'}:6: transition t0: qw = 'x' "
                             "failed (text)"]
    assert diag.count == 2


def test_refresh_outputs_rewrites_a_busy_transitions_output(tmp_path: Path) -> None:
    """After an outside write (an HMI's, a force's end) every place-driven and busy output is
    written again from the net: a transition busy in its duration drives its output on."""
    net = compile_program(tmp_path, DURATION)
    engine = Engine(net)
    assert ("r", 1) in engine.fire_round(Ctx(), 0).writes  # work starts: busy, r on
    assert engine.fire_round(Ctx(), 10).writes == ()  # nothing changed: nothing written
    engine.refresh_outputs()
    assert ("r", 1) in engine.fire_round(Ctx(), 20).writes  # still busy: r on again
