"""Repeats of one event counted in windows: the rule that keeps a flood out of a bounded log.

Owns: per key, a window opened by its first event (which the caller reports at once); the
events of that key within `window_s` are counted (how many, the first and last times, the
last payload and how often it changed, how many of each kind) and handed back together when
the window closes; a key still busy then opens the next window without a report of its own,
an idle one is forgotten. At most `max_keys` keys (`max_keys_per_peer` of one peer) are
open: events beyond are counted per class into one tally naming up to PEERS_NAMED peers.
Pure: times are arguments. Room walls: hmi and api both use it, and both may import core.
Does not know: what the events are (hmi/coalesce.py: Modbus writes; security/refusals.py:
refused HTTP requests), how a tally becomes a record, files, clocks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any, Final, Generic, TypeVar

PEERS_NAMED: Final = 8  # in a tally of events beyond the keys
KINDS_NAMED: Final = 8  # kinds counted one by one in a tally; the others together

K = TypeVar("K", bound=Hashable)


@dataclass(slots=True)
class Tally:
    """The events of one key (or, `beyond`, of keys that found no room) since their last
    report. `entry` is the caller's record of the first event (who and what)."""

    entry: dict[str, Any]
    ends_s: float
    payload: Any = None  # of the last event: `changed` compares with it
    beyond: bool = False
    count: int = 0
    changed: int = 0
    first_s: float = 0.0
    last_s: float = 0.0
    kinds: dict[str, int] = field(default_factory=dict)
    other_kinds: int = 0
    peers: list[str] = field(default_factory=list)
    more_peers: int = 0

    def add(self, now_s: float, payload: Any = None, kind: str | None = None,
            peer: str | None = None) -> None:
        if self.count == 0:
            self.first_s = now_s
        self.count += 1
        self.changed += payload != self.payload
        self.payload, self.last_s = payload, now_s
        if kind is not None:
            if kind in self.kinds or len(self.kinds) < KINDS_NAMED:
                self.kinds[kind] = self.kinds.get(kind, 0) + 1
            else:
                self.other_kinds += 1
        if peer is not None and peer not in self.peers:
            if len(self.peers) < PEERS_NAMED:
                self.peers.append(peer)
            else:
                self.more_peers += 1

    def times(self, now_s: float, wall_s: float,
              text: Callable[[float], str]) -> dict[str, str]:
        """`first` and `last` on the wall clock, `now_s` being its `wall_s`, written by
        `text` (the caller's format: core reads no clock and formats no dates)."""
        return {"first": text(wall_s - (now_s - self.first_s)),
                "last": text(wall_s - (now_s - self.last_s))}


class Repeats(Generic[K]):
    """The open windows of one source of events."""

    def __init__(self, window_s: float, max_keys: int, max_keys_per_peer: int) -> None:
        self.window_s = window_s
        self._max_keys = max_keys
        self._max_per_peer = max_keys_per_peer
        self._open: dict[K, tuple[str, Tally]] = {}
        self._per_peer: dict[str, int] = {}
        self._beyond: dict[Hashable, Tally] = {}

    @property
    def open(self) -> int:
        """Windows open (a timer must call `due` while there are any)."""
        return len(self._open) + len(self._beyond)

    def again(self, key: K, now_s: float, payload: Any = None, kind: str | None = None) -> bool:
        """Count an event of `key` into its open window: True; False when it has none."""
        found = self._open.get(key)
        if found is None:
            return False
        found[1].add(now_s, payload, kind)
        return True

    def first(self, key: K, peer: str, entry: dict[str, Any], now_s: float,
              payload: Any = None, *, counted: bool = False) -> bool:
        """Open a window for the first event of `key` (reported by the caller, or `counted`
        in the window when it cannot be now): True; False when there is no room for it."""
        if len(self._open) >= self._max_keys or \
                self._per_peer.get(peer, 0) >= self._max_per_peer:
            return False
        tally = Tally(entry, now_s + self.window_s, payload)
        if counted:
            tally.add(now_s, payload)
        self._open[key] = (peer, tally)
        self._per_peer[peer] = self._per_peer.get(peer, 0) + 1
        return True

    def beyond(self, klass: Hashable, peer: str, now_s: float,
               entry: Callable[[], dict[str, Any]], kind: str | None = None) -> None:
        """Count an event that found no window, in the tally of its class (`entry` makes
        that tally's record when it is the first)."""
        tally = self._beyond.get(klass)
        if tally is None:
            tally = self._beyond[klass] = Tally(entry(), now_s + self.window_s, beyond=True)
        tally.add(now_s, kind=kind, peer=peer)

    def due(self, now_s: float) -> list[Tally]:
        """The tallies of the windows closed by `now_s` that counted anything."""
        closed: list[Tally] = []
        for key, (_, tally) in list(self._open.items()):
            if tally.ends_s > now_s:
                continue
            if tally.count:
                closed.append(dataclasses.replace(tally))
                tally.count = tally.changed = tally.other_kinds = 0
                tally.kinds = {}
                tally.ends_s = now_s + self.window_s
            else:
                self._forget(key)
        for klass, tally in list(self._beyond.items()):
            if tally.ends_s <= now_s:
                closed.append(tally)
                del self._beyond[klass]
        return closed

    def drain(self) -> list[Tally]:
        """Every tally that counted anything (at stop); nothing stays open."""
        closed = [t for _, t in self._open.values() if t.count]
        closed += self._beyond.values()
        self._open.clear()
        self._per_peer.clear()
        self._beyond.clear()
        return closed

    def _forget(self, key: K) -> None:
        peer = self._open.pop(key)[0]
        left = self._per_peer[peer] - 1
        if left:
            self._per_peer[peer] = left
        else:
            del self._per_peer[peer]
