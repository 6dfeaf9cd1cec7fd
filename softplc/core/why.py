"""Why a transition fires or does not, in one firing round (issue 32, item 1).

Owns: the explanation of a transition at one round, as the round itself decides it: the
round is run again on a copy of the state by the engine (core/engine/), so what this says
fires is what the round fires; the reasons (a place short of tokens, a test or inhibitor arc,
a capacity, a timed firing in progress, the guard with the values it read, an enabling delay,
a conflict lost, forced values) are read off the same net, marking and context; values are
written by core/present.py (a real as a real, a scaled symbol in engineering units).
Does not know: where the state comes from (a running PLC's board, a replayed trace), clocks,
HTTP. Costs nothing to a scan: it is only called when someone asks.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from softplc.core.engine import Engine
from softplc.core.engine.step import Step
from softplc.core.expr import EvalContext
from softplc.core.net import CompiledNet, NetState, Transition
from softplc.core.present import raw_text
from softplc.core.problems import PlcFault
from softplc.core.whyguard import guard_reasons

FIRES: Final = "fires"  # in the step of this round
BLOCKED: Final = "blocked"  # not enabled: marking, capacity, busy or guard
WAITING: Final = "waiting"  # enabled, its enabling delay not elapsed
LOST: Final = "lost"  # a candidate that the step left too little for (a conflict)
ERROR: Final = "error"  # the round itself faults (a limit): nothing fires
MAX_FEEDERS: Final = 3  # transitions named per short place


@dataclass(frozen=True, slots=True)
class Reason:
    """One thing that decides: `kind` is tokens, test, inhibitor, capacity, busy, guard,
    delay, conflict, forced, fires or fault; `place`/`symbols` name what it is about."""

    kind: str
    text: str
    place: str | None = None
    symbols: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind, "text": self.text}
        if self.place is not None:
            out["place"] = self.place
        if self.symbols:
            out["symbols"] = list(self.symbols)
        return out


@dataclass(frozen=True, slots=True)
class Why:
    """The verdict on one transition and its reasons; `feeders` explain the transitions that
    put tokens on a place it lacks (one level)."""

    transition: str
    verdict: str
    reasons: tuple[Reason, ...]
    feeders: tuple[Why, ...] = ()

    @property
    def fires(self) -> bool:
        return self.verdict == FIRES

    def as_dict(self) -> dict[str, Any]:
        return {"transition": self.transition, "verdict": self.verdict, "fires": self.fires,
                "reasons": [r.as_dict() for r in self.reasons],
                "feeders": [f.as_dict() for f in self.feeders]}


@dataclass(frozen=True, slots=True)
class Round:
    """The round as the engine runs it on a copy: candidates, who was ready (enabled, with
    the time since), the step; or the fault that stopped it."""

    net: CompiledNet
    state: NetState  # the marking M_k the round starts from (not modified)
    ctx: EvalContext
    now_ns: int
    forced: Mapping[str, object]  # symbol -> the forced raw bits (core/forcing.py `values`)
    candidates: frozenset[int]
    since: Mapping[int, int]
    step: Step | None
    fault: str = ""


def run_round(net: CompiledNet, state: NetState, ctx: EvalContext, now_ns: int,
              forced: Mapping[str, object] | None = None) -> Round:
    """The round at `now_ns` from `state` on `ctx`, run on a copy (`state` is unchanged)."""
    engine = Engine(net, state.copy())
    try:
        candidates = frozenset(engine.candidates(ctx, now_ns))
        since = dict(engine.state.enabled_since)
        step = engine.fire_round(ctx, now_ns)
    except PlcFault as exc:
        return Round(net, state, ctx, now_ns, forced or {}, frozenset(), {}, None, exc.reason)
    return Round(net, state, ctx, now_ns, forced or {}, candidates, since, step)


def explain(net: CompiledNet, state: NetState, ctx: EvalContext, now_ns: int, name: str,
            forced: Mapping[str, object] | None = None) -> Why:
    """Why transition `name` fires or not in the round at `now_ns` from `state` (M_k) on
    `ctx` (the round's image and events). KeyError for an unknown transition."""
    return why(run_round(net, state, ctx, now_ns, forced), name)


def why(rnd: Round, name: str, depth: int = 1) -> Why:
    """The explanation of `name` in an already run round; `depth` levels of feeders."""
    t = rnd.net.transition(name)
    forced = _forced(rnd, t)
    if rnd.step is None:
        return Why(name, ERROR, (Reason("fault", f"the round faults: {rnd.fault}"), *forced))
    if t.index in rnd.step.fired:
        text = "fires in this round" + (" (its timed firing starts)" if t.duration_ns else "")
        return Why(name, FIRES, (Reason("fires", text), *forced))
    blockers = _blockers(rnd, t)
    if blockers:
        return Why(name, BLOCKED, (*blockers, *forced), _feeders(rnd, blockers, depth))
    if t.index in rnd.candidates:
        return Why(name, LOST, (*_conflict(rnd, t), *forced))
    if t.index in rnd.since and t.delay_ns:
        elapsed = rnd.now_ns - rnd.since[t.index]
        text = f"enabling delay: {_ms(elapsed)} of {_ms(t.delay_ns)} ms elapsed"
        return Why(name, WAITING, (Reason("delay", text), *forced))
    text = "not enabled in this round (no binding of its token variables fits)"
    return Why(name, BLOCKED, (Reason("guard", text), *forced))


def _blockers(rnd: Round, t: Transition) -> list[Reason]:
    """What keeps `t` from being enabled on M_k, in the order the round checks it."""
    net, state = rnd.net, rnd.state
    m, names = state.marking, net.place_names
    out: list[Reason] = []
    busy = state.busy.get(t.index)
    if busy is not None:
        left = max(busy.end_ns - rnd.now_ns, 0)
        out.append(Reason("busy", f"a timed firing in progress: {_ms(left)} of "
                                  f"{_ms(t.duration_ns)} ms left"))
    for a in t.pre:
        if m[a.place] < a.weight:
            out.append(Reason("tokens", f"{names[a.place]}: {int(m[a.place])} of {a.weight}",
                              names[a.place]))
    for p, w in t.test:
        if m[p] < w:
            out.append(Reason("test", f"{names[p]}: {int(m[p])} of {w} (read arc)", names[p]))
    for p, w in t.inhibit:
        if m[p] >= w:
            out.append(Reason("inhibitor", f"{names[p]}: {int(m[p])} token(s), inhibitor arc "
                                           f"of weight {w}", names[p]))
    out += _capacity(rnd, t)
    if not out or not t.coloured:  # a coloured guard needs tokens to bind: only then
        out += [Reason("guard", text, symbols=read)
                for text, read in guard_reasons(rnd.net, state, rnd.ctx, t, rnd.forced)]
    return out


def _capacity(rnd: Round, t: Transition) -> list[Reason]:
    """The capacity rule of core/engine/capacity.py, with the figures."""
    net, state = rnd.net, rnd.state
    out = []
    for arc in t.post:
        cap = int(net.capacity[arc.place])
        if cap < 0:
            continue
        consumed = sum(a.weight for a in t.pre if a.place == arc.place)
        due = sum(count for b in state.busy.values() for place, count, _ in b.produce
                  if place == arc.place)
        now = int(state.marking[arc.place])
        if now + due - consumed + arc.weight > cap:
            reserved = f" + {due} reserved by timed firings" if due else ""
            out.append(Reason("capacity", f"{net.place_names[arc.place]}: capacity {cap} "
                              f"full ({now}{reserved} - {consumed} taken + {arc.weight} put)",
                              net.place_names[arc.place]))
    return out


def _conflict(rnd: Round, t: Transition) -> list[Reason]:
    """A candidate the step did not take: the transitions before it that took from its
    places (priority first, then declaration order)."""
    assert rnd.step is not None
    net, names = rnd.net, rnd.net.place_names
    wanted = {a.place for a in t.pre}
    out = []
    for ti in rnd.step.fired:
        winner = net.transitions[ti]
        shared = sorted(wanted & {a.place for a in winner.pre})
        if shared:
            order = (f"priority {winner.priority} over {t.priority}"
                     if winner.priority != t.priority else "same priority, declared first")
            places = ", ".join(names[p] for p in shared)
            out.append(Reason("conflict", f"conflict lost to {winner.name} on {places} "
                              f"({order})", names[shared[0]]))
    if not out:
        out.append(Reason("conflict", "a candidate, but the transitions taken before it left "
                                      "too little (tokens, capacity or coloured tokens)"))
    return out


def _forced(rnd: Round, t: Transition) -> list[Reason]:
    """Forced symbols this transition reads (its guard) or drives (actions, busy outputs)."""
    if not rnd.forced:
        return []
    read = set(t.guard.reads) if t.guard is not None else set()
    driven = {a.target for a in t.actions} | {s for s, _ in t.busy_outputs}
    out = []
    for symbol in sorted((read | driven) & set(rnd.forced)):
        role = "read by its guard" if symbol in read else "driven by it: the force wins"
        value = rnd.forced[symbol]
        sym = rnd.net.io.symbols.get(symbol)
        if sym is not None and isinstance(value, int) and not isinstance(value, bool):
            value = raw_text(sym.type.value, value, sym.scaling)
        out.append(Reason("forced", f"{symbol} is forced to {value} ({role})",
                          symbols=(symbol,)))
    return out


def _feeders(rnd: Round, blockers: list[Reason], depth: int) -> tuple[Why, ...]:
    """For the places short of tokens: the transitions that put tokens there, explained."""
    if depth <= 0:
        return ()
    net = rnd.net
    short = [r.place for r in blockers if r.kind in ("tokens", "test") and r.place]
    out: list[Why] = []
    for place in short:
        p = net.place_index[place]
        feeders = [u for u in net.transitions if any(o.place == p for o in u.post)]
        out += [why(rnd, u.name, depth - 1) for u in feeders[:MAX_FEEDERS]]
    return tuple(out)


def _ms(ns: int) -> str:
    return f"{ns / 1e6:.3f}".rstrip("0").rstrip(".")


def format_why(answer: Mapping[str, Any], indent: str = "", head: str = "") -> list[str]:
    """An explanation as a person reads it (Why.as_dict() or the API's answer): one line
    per reason, the feeders indented under it."""
    lines = [f"{indent}{head}{answer.get('transition')}: {answer.get('verdict')}"]
    lines += [f"{indent}  - {r.get('text')}" for r in answer.get("reasons") or []]
    for feeder in answer.get("feeders") or []:
        lines += format_why(feeder, indent + "    ", "fed by ")
    return lines
