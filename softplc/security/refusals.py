"""Requests refused at the HTTP gate, in the audit trail without flooding it.

Owns: `Refusals`, the rule of docs/security.md ("Refused requests"), core/repeats.py's
windows keyed by (peer, user, via, role, outcome, status, why: a failed login's reason or
the role a denied request needed): the first refusal of a key is a record at once
(`refusals` 1), its repeats within `window_s` one record at the window's close (`refusals`,
`first`, `last`, `routes`: how many of each route, 8 named, `other_routes`). The route is
counted, not keyed: a client varies it at will. At most MAX_KEYS keys (MAX_KEYS_PER_PEER of
one peer); refusals beyond are counted per (outcome, status) into one record naming their
peers. `RefusalAudit`: that rule on one server's loop, a timer closing its windows while
any is open, every count written at stop.
Does not know: credentials and roles (access.py hands in the records), the trail's format
(the writer it is handed appends).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import Awaitable, Callable
from typing import Any, Final

from softplc.core.repeats import Repeats, Tally
from softplc.security.audit import utc_text

WINDOW_S: Final = 10.0  # a key refused on and on: one record per window
MAX_KEYS: Final = 256
MAX_KEYS_PER_PEER: Final = 16  # one address cannot push the others out of itemized records
TICK_S: Final = 1.0  # how often open windows are looked at (at most)

Writer = Callable[[dict[str, Any]], Awaitable[None]]


class Refusals:
    """The records of one gate's refusals (pure: times are arguments)."""

    def __init__(self, window_s: float = WINDOW_S, max_keys: int = MAX_KEYS,
                 max_keys_per_peer: int = MAX_KEYS_PER_PEER) -> None:
        self._max_keys = max_keys
        self._max_per_peer = max_keys_per_peer
        self._repeats: Repeats[str] = Repeats(window_s, max_keys, max_keys_per_peer)

    @property
    def window_s(self) -> float:
        return self._repeats.window_s

    @window_s.setter
    def window_s(self, value: float) -> None:
        self._repeats.window_s = value

    @property
    def open(self) -> int:
        return self._repeats.open

    def note(self, entry: dict[str, Any], route: str, now_s: float) -> dict[str, Any] | None:
        """One refused request (`entry`: its record as the gate would write it; `route`:
        METHOD /path): the record to write now, or None when it is counted for a later one."""
        peer = str(entry.get("peer"))
        detail = {k: v for k, v in entry["detail"].items() if k != "route"}
        key = json.dumps([entry.get(k) for k in ("peer", "user", "via", "role", "outcome",
                                                 "status")] + [detail], sort_keys=True)
        if self._repeats.again(key, now_s, kind=route):
            return None
        if not self._repeats.first(key, peer, entry, now_s):
            self._repeats.beyond((entry["outcome"], entry["status"]), peer, now_s,
                                 lambda: self._beyond_entry(entry), kind=route)
            return None
        return {**entry, "detail": {**entry["detail"], "refusals": 1}}

    def _beyond_entry(self, entry: dict[str, Any]) -> dict[str, Any]:
        return {"user": None, "role": None, "via": None, "peer": entry.get("peer"),
                "iface": entry["iface"], "action": entry["action"],
                "outcome": entry["outcome"], "status": entry["status"],
                "detail": {"beyond_keys": self._max_keys,
                           "beyond_keys_per_peer": self._max_per_peer}}

    def due(self, now_s: float, wall_s: float) -> list[dict[str, Any]]:
        """The records of the windows closed by `now_s` (`wall_s`: the wall clock then)."""
        return [_summary(t, now_s, wall_s) for t in self._repeats.due(now_s)]

    def drain(self, now_s: float, wall_s: float) -> list[dict[str, Any]]:
        """Every count not recorded yet (at stop); nothing stays open."""
        return [_summary(t, now_s, wall_s) for t in self._repeats.drain()]


def _summary(tally: Tally, now_s: float, wall_s: float) -> dict[str, Any]:
    """"N more refusals of this key between first and last", and on which routes."""
    counts = {"refusals": tally.count, **tally.times(now_s, wall_s, utc_text),
              "routes": tally.kinds, "other_routes": tally.other_kinds}
    if tally.beyond:
        counts.update(peers=tally.peers, more_peers=tally.more_peers)
        return {**tally.entry, "peer": tally.peers[0],
                "detail": {**tally.entry["detail"], **counts}}
    return {**tally.entry, "detail": {**tally.entry["detail"], **counts}}


class RefusalAudit:
    """The refusals of one server, on its loop; records go to `write` (an append in a
    thread), the first of a key before the refusal is answered, the others from a timer."""

    def __init__(self, write: Writer, window_s: float = WINDOW_S) -> None:
        self.rule = Refusals(window_s)
        self._write = write
        self._timer: asyncio.TimerHandle | None = None
        self._writing: set[asyncio.Task[None]] = set()

    async def refused(self, entry: dict[str, Any], route: str) -> None:
        loop = asyncio.get_running_loop()
        record = self.rule.note(entry, route, loop.time())
        if self._timer is None and self.rule.open:
            self._timer = loop.call_later(self._tick_s(), self._tick)
        if record is not None:
            await self._write(record)

    def _tick_s(self) -> float:
        return min(TICK_S, self.rule.window_s / 4)

    def _tick(self) -> None:
        loop = asyncio.get_running_loop()
        self._timer = None
        records = self.rule.due(loop.time(), time.time())
        if records:
            task = loop.create_task(self._write_all(records))
            self._writing.add(task)
            task.add_done_callback(self._writing.discard)
        if self.rule.open:
            self._timer = loop.call_later(self._tick_s(), self._tick)

    async def _write_all(self, records: list[dict[str, Any]]) -> None:
        for record in records:
            await self._write(record)

    async def close(self) -> None:
        """Write every count still open and wait until the trail has them (at stop)."""
        loop = asyncio.get_running_loop()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.gather(*self._writing)
        await self._write_all(self.rule.drain(loop.time(), time.time()))
