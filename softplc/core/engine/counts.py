"""The token-count limits (core/limits.py) as a round meets them.

Owns: the counts per place and in total after a round that may have grown them, and room
for coloured records reserved before they are built (per place and in total).
Does not know: which round grows the net (produce.py decides when to check), enabling.
"""

from __future__ import annotations

import numpy as np

from softplc.core.engine.live import Live
from softplc.core.net import CompiledNet
from softplc.core.problems import FaultCode, PlcFault

SMALL_NET = 64  # places: below this a Python reduction is cheaper than a numpy call


class Counts:
    """Raises PlcFault(FaultCode.LIMIT, ...) naming the place or transition at fault."""

    __slots__ = ("_coloured_now", "_live", "_net", "_planned")

    def __init__(self, net: CompiledNet, live: Live) -> None:
        self._net, self._live = net, live
        self._planned: dict[int, int] = {}  # coloured place -> records reserved this round
        self._coloured_now = 0  # records in the net when this round's productions began

    def check(self) -> None:
        """Tokens per place and in total after a round that may have grown them: two
        reductions over the marking (numpy for a large net, where a call's overhead pays)."""
        lim, m = self._net.limits, self._live.view()
        if not len(m):
            return
        if len(m) > SMALL_NET:
            marking = np.asarray(self._live.state.marking)
            total, count = int(marking.sum()), int(marking.max())
        else:
            total, count = sum(m), max(m)
        self._live.high = total > lim.place_tokens
        if count <= lim.place_tokens and total <= lim.total_tokens:
            return
        fullest = self._net.place_names[list(m).index(count)]
        if count > lim.place_tokens:
            raise PlcFault(FaultCode.LIMIT, (
                f"place {fullest}: {count:,} tokens exceed the limit "
                f"{lim.place_tokens:,} (limits.place_tokens)"))
        raise PlcFault(FaultCode.LIMIT, (
            f"net {self._net.name}: {total:,} tokens exceed the limit {lim.total_tokens:,} "
            f"(limits.total_tokens; most in place {fullest})"))

    def begin(self) -> None:
        """A round's productions begin: nothing reserved yet, the records counted."""
        tokens = self._live.state.tokens
        self._planned = {}
        self._coloured_now = sum(map(len, tokens.values())) if tokens else 0

    def reserve(self, who: str, place: int, records: int) -> None:
        """Room for `records` more records in coloured `place` this round, checked before
        they are built: the limit holds long before memory runs out."""
        lim, planned, net = self._net.limits, self._planned, self._net
        planned[place] = planned.get(place, 0) + records
        count = len(self._live.state.tokens.get(place, ())) + planned[place]
        if count > lim.coloured_place:
            raise PlcFault(FaultCode.LIMIT, (
                f"place {net.place_names[place]}: {count:,} coloured tokens exceed the "
                f"limit {lim.coloured_place:,} (limits.coloured_place; {who})"))
        self._coloured_now += records
        if self._coloured_now > lim.coloured_total:
            raise PlcFault(FaultCode.LIMIT, (
                f"net {net.name}: {self._coloured_now:,} coloured tokens exceed the limit "
                f"{lim.coloured_total:,} (limits.coloured_total; {who} into place "
                f"{net.place_names[place]})"))
