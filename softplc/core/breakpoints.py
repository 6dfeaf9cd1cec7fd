"""Breakpoints and single scans (docs/debug.md): when a RUNNING PLC pauses, and what a pause is.

Owns: Breakpoint (a transition fires, a transition becomes enabled, a condition over marking
and symbols becomes true: the guards' sandboxed expressions, core/expr.py, with `m("place")`
for a place's marking), Pause (the breakpoints that hit, the scan, the output policy, the net
time it froze), Breakpoints (the list, the pause, the scans a step still runs) and the time
rule: a scan run after a pause sees its net time one period after the scan before it.
Does not know: the order of a scan (core/scan.py), Plc (core/plc.py and core/pausing.py hand
it values), clocks, processes.
"""

from __future__ import annotations

import ast
import difflib
import enum
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from softplc.core.errors import SoftplcError
from softplc.core.expr import (
    Compiled,
    EvalContext,
    ExprError,
    NameKind,
    Scope,
    Value,
    compile_expr,
    name_kind,
    parse,
)
from softplc.core.held import HeldOutputs
from softplc.core.net import CompiledNet, IntArray, NetState, Transition


class On(enum.Enum):
    FIRE = "fire"  # the transition is in the step of a round
    ENABLED = "enabled"  # it becomes enabled (arcs, capacities, guard) at the end of a scan
    WHEN = "when"  # a condition becomes true at the end of a scan


class Outputs(enum.Enum):
    """What the devices get while the PLC is paused."""

    HOLD = "hold"  # the outputs of the scan that paused, as CODESYS at a breakpoint
    SAFE = "safe"  # the declared safe values; the program's own come back when it runs


def strictest(policies: Iterable[Outputs], default: Outputs = Outputs.HOLD) -> Outputs:
    """The policy of a pause several breakpoints hit: `safe` if any of them asks for it.
    Outputs someone asked to be safe are never held because another breakpoint hit too,
    whatever their order or ids (issue 38 item 7)."""
    return Outputs.SAFE if Outputs.SAFE in {default, *policies} else Outputs.HOLD


class BreakRefused(SoftplcError):
    """A breakpoint that cannot be set or removed (the reason for people)."""


@dataclass(frozen=True, slots=True)
class Breakpoint:
    id: int
    on: On
    target: str  # the transition's name, or the condition's text as given
    outputs: Outputs = Outputs.HOLD
    index: int = -1  # the transition's index in the net it is bound to
    condition: Compiled | None = field(default=None, compare=False, repr=False)
    places: Mapping[str, int] = field(default_factory=dict, compare=False, repr=False)

    def describe(self) -> str:
        what = {On.FIRE: "fires", On.ENABLED: "becomes enabled", On.WHEN: "becomes true"}
        return f"b{self.id}: {self.target} {what[self.on]}"

    def as_dict(self) -> dict[str, Any]:
        return {"id": self.id, "on": self.on.value, "target": self.target,
                "outputs": self.outputs.value, "text": self.describe()}


def spec(on: On, target: str) -> str:
    """A breakpoint as the command carries it: `fire:NAME`, `enabled:NAME`, `when:EXPR`."""
    return f"{on.value}:{target}"


def parse_spec(text: str) -> tuple[On, str]:
    kind, sep, target = text.partition(":")
    try:
        on = On(kind.strip())
    except ValueError:
        raise BreakRefused(f"unknown breakpoint kind {kind!r}: fire, enabled or when") from None
    if not sep or not target.strip():
        raise BreakRefused(f"breakpoint {text!r} names no transition or condition")
    return on, target.strip()


@dataclass(frozen=True, slots=True)
class Pause:
    """The PLC paused at the end of scan `k` (the trace's and the timeline's scan number;
    `scan_count` = k + 1 scans have run), with its net time frozen at `net_ns`."""

    k: int
    net_ns: int
    outputs: Outputs
    hit: tuple[Breakpoint, ...] = ()  # empty: the end of a step
    steps: int = 0  # the step of this many scans that ended here (0: a breakpoint hit)

    def reason(self) -> str:
        hits = "; ".join(b.describe() for b in self.hit)
        if self.steps:
            done = f"step of {self.steps} scan(s) done"
            return done + (f" (hit meanwhile: {hits})" if hits else "")
        return hits

    def as_dict(self) -> dict[str, Any]:
        return {"k": self.k, "scan_count": self.k + 1, "reason": self.reason(),
                "breakpoints": [b.as_dict() for b in self.hit], "steps": self.steps,
                "outputs": self.outputs.value}


class _Marked:
    """The condition's EvalContext: the scan's symbols, and the marking under `m("...")`."""

    __slots__ = ("ctx", "marking", "places")

    def __init__(self, ctx: EvalContext, marking: IntArray, places: Mapping[str, int]) -> None:
        self.ctx, self.marking, self.places = ctx, marking, places

    def symbol(self, name: str) -> int | float:
        place = self.places.get(name)
        return self.ctx.symbol(name) if place is None else int(self.marking[place])

    def previous(self, name: str) -> int | float:
        return self.ctx.previous(name)

    def event(self, name: str) -> bool:
        return self.ctx.event(name)

    def token(self, var: str) -> Mapping[str, Value]:
        raise KeyError(var)


def compile_condition(text: str, net: CompiledNet) -> tuple[Compiled, dict[str, int]]:
    """`text` in the guards' language over `net`'s symbols and events, where `m("p")` is place
    p's marking. Each `m("p")` becomes a name of its own (m0, m1, ... not taken by a symbol)
    read from the marking. Raises ExprError naming what is wrong."""
    taken = set(net.io.symbols) | set(net.io.events) | set(net.emits)
    places: dict[str, int] = {}
    by_place: dict[str, str] = {}

    class Marking(ast.NodeTransformer):
        def visit_Call(self, node: ast.Call) -> ast.AST:
            self.generic_visit(node)
            if not (isinstance(node.func, ast.Name) and node.func.id == "m"):
                return node
            arg = node.args[0] if len(node.args) == 1 and not node.keywords else None
            if not (isinstance(arg, ast.Constant) and isinstance(arg.value, str)):
                raise ExprError('m() takes one place name in quotes: m("c1.full")')
            place = arg.value
            if place not in net.place_index:
                near = difflib.get_close_matches(place, net.place_names, 1)
                raise ExprError(f"unknown place {place!r} in program {net.name}"
                                + (f" (did you mean {near[0]!r}?)" if near else ""))
            if place not in by_place:
                n = len(by_place)
                while f"m{n}" in taken:
                    n += 1
                by_place[place] = name = f"m{n}"
                taken.add(name)
                places[name] = net.place_index[place]
            return ast.copy_location(ast.Name(id=by_place[place], ctx=ast.Load()), node)

    tree = Marking().visit(parse(text))
    names = {s.name: name_kind(s.type) for s in net.io.symbols.values()}
    names.update(dict.fromkeys([*net.io.events, *net.emits], NameKind.EVENT))
    names.update(dict.fromkeys(places, NameKind.WORD))
    return compile_expr(ast.unparse(tree), Scope(names)), places


def enabled(net: CompiledNet, state: NetState, t: Transition, ctx: EvalContext) -> bool:
    """`t` enabled on `state`'s marking and `ctx`'s values: not busy, its input and test arcs
    met, no inhibitor marked, room in capped places, its guard true (a coloured transition:
    its arcs only). What the next round would find, its enabling delay aside."""
    m = state.marking
    if t.index in state.busy:
        return False
    if any(m[a.place] < a.weight for a in t.pre) or any(m[p] < w for p, w in t.test):
        return False
    if any(m[p] >= w for p, w in t.inhibit):
        return False
    cap = net.capacity
    for out in t.post:
        taken = sum(a.weight for a in t.pre if a.place == out.place)
        if cap[out.place] >= 0 and m[out.place] - taken + out.weight > cap[out.place]:
            return False
    if t.guard is None or t.coloured:
        return True
    try:
        return bool(t.guard(ctx))
    except Exception:  # a guard that raises is false for that scan (docs/design.md 3)
        return False


class Breakpoints:
    """The breakpoints of one PLC, its pause and the scans a step still has to run.

    `period_ns` is the scan period (the runtime sets it; 0: unknown, then a scan after a pause
    sees the time since the last paused cycle, `cycle_ns`)."""

    def __init__(self) -> None:
        self.items: dict[int, Breakpoint] = {}
        self.next_id = 1
        self.pause: Pause | None = None
        self.steps_left = 0  # scans a step still runs before the PLC pauses again
        self.period_ns = 0
        self.cycle_ns = 0  # the last paused cycle's time
        self.held: HeldOutputs | None = None  # the program's outputs while `safe` is out
        self.notes: list[str] = []  # breakpoints dropped by a download, for its reply
        self._was: dict[int, bool] = {}  # enabled / true at the end of the last scan
        self._step: tuple[int, Outputs] | None = None  # the running step: its size, policy
        self._step_hits: list[Breakpoint] = []

    @property
    def paused(self) -> bool:
        """Paused (a step running is not): the scan runs no round, the net's time stands."""
        return self.pause is not None

    @property
    def armed(self) -> bool:
        """Something to look at after a round: a breakpoint, or a step running."""
        return bool(self.items) or bool(self.steps_left)

    def add(self, on: On, target: str, outputs: Outputs, net: CompiledNet,
            state: NetState | None, ctx: EvalContext | None) -> Breakpoint:
        point = self._bind(Breakpoint(self.next_id, on, target, outputs), net)
        self.next_id += 1
        self.items[point.id] = point
        self._was[point.id] = self._holds(point, net, state, ctx)  # a pause needs a change
        return point

    def remove(self, ident: int | None) -> list[Breakpoint]:
        """One breakpoint (None: every one); an unknown id is refused."""
        if ident is not None and ident not in self.items:
            known = ", ".join(f"b{i}" for i in self.items) or "none"
            raise BreakRefused(f"no breakpoint b{ident} (set: {known})")
        gone = [self.items.pop(i) for i in ([ident] if ident is not None else list(self.items))]
        for point in gone:
            self._was.pop(point.id, None)
        return gone

    def rebind(self, net: CompiledNet) -> None:
        """A program was loaded: each breakpoint bound to it again; those it cannot take (a
        transition, place or symbol it lacks) are dropped, with a note for the reply."""
        for ident, point in list(self.items.items()):
            try:
                self.items[ident] = self._bind(point, net)
            except (BreakRefused, ExprError) as exc:
                del self.items[ident]
                self._was.pop(ident, None)
                self.notes.append(f"breakpoint {point.describe()} dropped: {exc}")

    def noted(self) -> str:
        notes, self.notes = self.notes, []
        return "".join(f"; {note}" for note in notes)

    @staticmethod
    def _bind(point: Breakpoint, net: CompiledNet) -> Breakpoint:
        if point.on is On.WHEN:
            try:
                condition, places = compile_condition(point.target, net)
            except ExprError as exc:
                raise BreakRefused(f"condition {point.target!r}: {exc.message}") from None
            return Breakpoint(point.id, point.on, point.target, point.outputs, -1, condition,
                              places)
        found = next((t for t in net.transitions if t.name == point.target), None)
        if found is None:
            near = difflib.get_close_matches(point.target, [t.name for t in net.transitions], 1)
            raise BreakRefused(f"no transition {point.target!r} in program {net.name}"
                               + (f" (did you mean {near[0]!r}?)" if near else ""))
        return Breakpoint(point.id, point.on, point.target, point.outputs, found.index)

    def _holds(self, point: Breakpoint, net: CompiledNet, state: NetState | None,
               ctx: EvalContext | None) -> bool:
        if point.on is On.FIRE or state is None or ctx is None:
            return False
        if point.on is On.ENABLED:
            return enabled(net, state, net.transitions[point.index], ctx)
        assert point.condition is not None
        try:
            return bool(point.condition(_Marked(ctx, state.marking, point.places)))
        except Exception:  # a condition that raises is false, as a guard is
            return False

    def after_scan(self, net: CompiledNet, state: NetState, ctx: EvalContext,
                   fired: Iterable[int], k: int, now_ns: int) -> Pause | None:
        """After the round of scan `k`: the pause this scan ends in, if it ends in one."""
        hits = self._hits(net, state, ctx, fired) if self.items else []
        if self.steps_left:  # a step running: exactly its scans, whatever hits meanwhile
            self.steps_left -= 1
            self._step_hits += hits
            if self.steps_left or self._step is None:
                return None
            (steps, outputs), self._step = self._step, None
            hit = tuple(self._step_hits)
            pause = Pause(k, now_ns, strictest((b.outputs for b in hit), outputs), hit, steps)
        elif hits and self.pause is None:
            pause = Pause(k, now_ns, strictest(b.outputs for b in hits), tuple(hits))
        else:
            return None
        self.pause, self.cycle_ns = pause, now_ns
        return pause

    def _hits(self, net: CompiledNet, state: NetState, ctx: EvalContext,
              fired: Iterable[int]) -> list[Breakpoint]:
        fired_set = set(fired)
        hits = []
        for point in self.items.values():
            if point.on is On.FIRE:
                if point.index in fired_set:
                    hits.append(point)
                continue
            now = self._holds(point, net, state, ctx)
            if now and not self._was.get(point.id, False):
                hits.append(point)
            self._was[point.id] = now
        return hits

    def leave(self, now_ns: int | None, steps: int = 0) -> tuple[int, HeldOutputs | None]:
        """The pause ends (steps > 0: for that many scans; a stop, kill or fault also ends a
        step running). Returns how far to shift the net's timers so that the next scan, at
        `now_ns`, is one period after the paused one in net time, and the outputs the `safe`
        policy put aside (to be put back)."""
        pause, self.pause = self.pause, None
        held, self.held = self.held, None
        self.steps_left, self._step, self._step_hits = 0, None, []
        if pause is None or now_ns is None:
            return 0, held
        if steps > 0:
            self.steps_left, self._step = steps, (steps, pause.outputs)
        return self._shift(pause, now_ns), held

    def frozen_shift(self, now_ns: int) -> int:
        """How far the net's timers move were the pause to end at `now_ns` (0: not paused):
        what a retain snapshot taken while paused applies, so that the pause does not exist
        for the net after a restart either (the time rule)."""
        return 0 if self.pause is None else self._shift(self.pause, now_ns)

    def _shift(self, pause: Pause, now_ns: int) -> int:
        if self.period_ns > 0:
            return now_ns - pause.net_ns - self.period_ns
        return self.cycle_ns - pause.net_ns

    def as_dict(self) -> dict[str, Any]:
        """For the status board: the breakpoints, the pause and a running step."""
        return {"breakpoints": [b.as_dict() for b in self.items.values()],
                "paused": self.pause.as_dict() if self.pause is not None else None,
                "steps_left": self.steps_left}
