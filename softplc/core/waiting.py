"""Why nothing moves: the transitions a running net has waited on longest, and what blocks them.

Owns (issue 39, deliver 6): per transition, since when (net time) the marking enables it
(its input, read and inhibitor arcs hold, no timed firing of it in progress) while it does
not fire; the longest such waits with what blocks each (the false parts of its guard with
the values read, a full capacity, its enabling delay); a dead marking (nothing enabled and
nothing in progress). After a reset with parts still on a plant's belts this names the
transition waiting for a sensor that the parts will never reach (docs/simulate.md).
Does not know: where the state comes from or when it is observed (runtime/statusdoc.py
observes at each status document, between scans), clocks, processes.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from softplc.core.expr import EvalContext
from softplc.core.net import CompiledNet, NetState, Transition
from softplc.core.whyguard import guard_reasons

SHOWN = 3  # waits listed, longest first
FIRST_LOOK = 256  # transitions checked per observation on a first look (~0.2 ms)


@dataclass(frozen=True, slots=True)
class Wait:
    """One transition enabled by the marking and not firing since `since_ns` (net time), or
    the whole net (`transition` None: a dead marking) since its last change."""

    transition: str | None
    since_ns: int
    for_s: float
    blockers: tuple[str, ...]
    symbols: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return {"transition": self.transition, "for_s": round(self.for_s, 3),
                "blockers": list(self.blockers), "symbols": list(self.symbols)}


def marking_enabled(net: CompiledNet, state: NetState, t: Transition) -> bool:
    """Its arcs allow it on the marking and no timed firing of it is in progress (the guard,
    capacity and delay are what a wait is explained by)."""
    m = state.marking
    return (t.index not in state.busy and all(m[a.place] >= a.weight for a in t.pre)
            and all(m[p] >= w for p, w in t.test) and all(m[p] < w for p, w in t.inhibit))


def first_look(net: CompiledNet, state: NetState) -> list[int]:
    """The transitions the marking may enable, highest index first (checked from the end):
    those reading a marked place and those without input or read arcs; every transition
    when the net does not say which have none (`unconditioned` None)."""
    if net.unconditioned is None:
        return list(range(len(net.transitions) - 1, -1, -1))
    touching = net.touching
    candidates = set(net.unconditioned).union(
        *(touching[p] for p in np.flatnonzero(state.marking).tolist()), state.busy)
    return sorted(candidates, reverse=True)


class Waits:
    """What one running net has waited on, observed between scans. `observe` at each look;
    `clear` when the PLC stops running (a start begins every wait anew)."""

    def __init__(self) -> None:
        self._net: CompiledNet | None = None
        self._state: NetState | None = None  # a new one: every wait begins anew
        self._marking = np.zeros(0, dtype=np.int64)  # the marking last observed
        self._busy: frozenset[int] = frozenset()  # and its timed firings in progress
        self._changed_ns = 0  # when either last changed
        self._enabled: set[int] = set()
        self._since: dict[int, int] = {}  # transition -> net time it began waiting
        self._fired: dict[int, int] = {}  # its firing count then
        self._unseen: list[int] = []  # the first look's transitions not checked yet

    def clear(self) -> None:
        self._net, self._state = None, None
        self._enabled, self._since, self._fired, self._unseen = set(), {}, {}, []

    @property
    def complete(self) -> bool:
        """Every transition the first look had to check has been checked."""
        return self._net is not None and not self._unseen

    def observe(self, net: CompiledNet, state: NetState, now_ns: int,
                fired: Mapping[str, int]) -> None:
        """Note the net at `now_ns` (net time): `fired` counts firings per transition name.
        Only the transitions touching a changed place are checked again. The first look at
        a net or state checks what the marking can enable (the transitions reading a marked
        place, and those without input or read arcs), at most FIRST_LOOK of them per
        observation: a whole check of 10,000 transitions took 7-46 ms here, on the scan
        thread in the scan that swapped the program in (issue 40 item 8)."""
        busy = frozenset(state.busy)
        todo: set[int]
        if net is not self._net or state is not self._state:  # a download, reset, start
            self.clear()
            self._net, self._state = net, state
            self._unseen = first_look(net, state)
            self._marking, self._busy, self._changed_ns = state.marking.copy(), busy, now_ns
            todo = set()
        else:
            changed = np.flatnonzero(state.marking != self._marking).tolist()
            todo = {ti for p in changed for ti in net.touching[p]} | (busy ^ self._busy)
            if todo or busy != self._busy:
                self._changed_ns = now_ns
                self._marking, self._busy = state.marking.copy(), busy
        if self._unseen:
            todo.update(self._unseen[-FIRST_LOOK:])
            del self._unseen[-FIRST_LOOK:]
        for ti in todo:
            if marking_enabled(net, state, net.transitions[ti]):
                self._enabled.add(ti)
            else:
                self._enabled.discard(ti)
        since, counts = {}, {}
        for ti in self._enabled:
            count = fired.get(net.transitions[ti].name, 0)
            kept = self._since.get(ti)
            since[ti] = kept if kept is not None and self._fired.get(ti) == count else now_ns
            counts[ti] = count
        self._since, self._fired = since, counts

    def longest(self, state: NetState, ctx: EvalContext, now_ns: int,
                forced: Mapping[str, object] | None = None) -> list[Wait]:
        """The SHOWN longest waits, longest first, each with its blockers; a dead marking as
        one wait of the whole net; [] before any observation."""
        net = self._net
        if net is None or self._unseen:  # not every candidate checked yet: nothing is known
            return []
        if not self._enabled:
            if state.busy:
                return []  # a timed firing in progress: it moves
            return [Wait(None, self._changed_ns, (now_ns - self._changed_ns) / 1e9, (
                "no transition is enabled by the marking (a dead marking: nothing can fire "
                "until a download or a reset)",))]
        order = sorted(self._since.items(), key=lambda item: (item[1], item[0]))[:SHOWN]
        out = []
        for ti, since_ns in order:
            t = net.transitions[ti]
            reasons = _blockers(net, state, ctx, t, now_ns, forced or {})
            out.append(Wait(t.name, since_ns, (now_ns - since_ns) / 1e9,
                            tuple(text for text, _ in reasons),
                            tuple(sorted({s for _, read in reasons for s in read}))))
        return out


def _blockers(net: CompiledNet, state: NetState, ctx: EvalContext, t: Transition,
              now_ns: int, forced: Mapping[str, object]) -> list[tuple[str, tuple[str, ...]]]:
    """What keeps a marking-enabled `t` from firing: its guard's false parts (with the values
    read), a full capacity, or its enabling delay; else a conflict (another took first)."""
    out = list(guard_reasons(net, state, ctx, t, forced))
    m = state.marking
    for arc in t.post:
        cap = int(net.capacity[arc.place])
        consumed = sum(a.weight for a in t.pre if a.place == arc.place)
        if cap >= 0 and int(m[arc.place]) - consumed + arc.weight > cap:
            out.append((f"{net.place_names[arc.place]}: capacity {cap} full", ()))
    if out:
        return out
    since = state.enabled_since.get(t.index)
    if t.delay_ns and since is not None:
        return [(f"enabling delay: {(now_ns - since) / 1e6:.0f} of {t.delay_ns / 1e6:.0f} ms "
                 "elapsed", ())]
    return [("enabled, but another transition took its tokens first (a conflict), or it "
             "fires in the next round", ())]
