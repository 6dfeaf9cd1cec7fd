"""The engine's step selection: the candidates that fire together in one round.

Owns: deterministic selection in priority order on the residual marking (each selected
transition takes its tokens before the next is tried), capacities against the step's
productions, and the coloured tokens a step's bindings reserve.
Does not know: how candidates are found (firing_enabling.py), what firing does.
"""

from __future__ import annotations

from softplc.core.expr import EvalContext
from softplc.core.firing_enabling import Enabling
from softplc.core.net import Transition


class Selection(Enabling):
    """Step selection on top of the enabling cache."""

    def _select(
        self, cands: list[int], ctx: EvalContext
    ) -> tuple[list[int], dict[int, dict[str, tuple[int, int]]]]:
        m, ts, pre, simple = self._view(), self.net.transitions, self._pre, self._simple
        residual: dict[int, int] = {}
        delta: dict[int, int] = {}
        track = bool(self._capped)  # only a capacity check reads delta
        taken: dict[int, set[int]] = {}  # coloured place -> token positions taken this round
        selected: list[int] = []
        bindings: dict[int, dict[str, tuple[int, int]]] = {}
        single = None if track else self._single_pre
        for ti in cands:
            one = single[ti] if single is not None else None
            if one is not None:  # simple, one input arc: the loops below in one comparison
                p, w = one
                left = residual.get(p, m[p]) - w
                if left >= 0:
                    residual[p] = left
                    selected.append(ti)
                continue
            arcs, fits = pre[ti], True
            for p, w in arcs:  # inline, not any(): a generator costs more than the test
                if residual.get(p, m[p]) < w:
                    fits = False
                    break
            if not fits:
                continue
            if not simple[ti]:
                t = ts[ti]
                if not self._fits_capacity(t, delta):
                    continue
                if t.coloured:
                    binding = self._bind(t, ctx, taken)
                    if binding is None:
                        continue
                    bindings[ti] = self._take(t, binding, taken)
            for p, w in arcs:
                residual[p] = residual.get(p, m[p]) - w
            if track:
                for p, w in arcs:
                    delta[p] = delta.get(p, 0) - w
                for o in ts[ti].post:
                    delta[o.place] = delta.get(o.place, 0) + o.weight
            selected.append(ti)
        return selected, bindings

    def _take(self, t: Transition, binding: dict[str, tuple[int, int]],
              taken: dict[int, set[int]]) -> dict[str, tuple[int, int]]:
        """Reserve the bound tokens, and for plain arcs from coloured places the oldest
        free ones (recorded under keys "#place#n"), so no other transition takes them."""
        positions = dict(binding)
        for place, index in binding.values():
            taken.setdefault(place, set()).add(index)
        for a in t.pre:
            if a.var is None and self.net.coloured[a.place]:
                used = taken.setdefault(a.place, set())
                free = (i for i in range(len(self.state.tokens.get(a.place, []))) if i not in used)
                for n, index in zip(range(a.weight), free, strict=False):
                    used.add(index)
                    positions[f"#{a.place}#{n}"] = (a.place, index)
        return positions
