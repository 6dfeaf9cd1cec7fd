"""What a Modbus write asks, and the rule that bounds the audit records of many writes.

Owns: the function codes that write and the description of a write request (function,
table, 0-based address, values); `Coalescer`, the rule of docs/security.md ("Audit of plain
Modbus writes"): per key (peer, unit, function, address, quantity, outcome) the first write
is a record at once, and the writes that follow within `window_s` are counted into one
record at the window's close carrying how many, how often the value changed, the last value
and the times of the first and last; a key still written at the close opens the next window
without a record of its own, an idle one is forgotten. At most `max_keys` keys (and
`max_keys_per_peer` of one peer) are open: writes beyond are counted per outcome into one
record naming their peers.
Does not know: sockets, clocks (times are arguments), the trail (records are returned).
"""

from __future__ import annotations

import datetime
import struct
from dataclasses import dataclass, field
from typing import Any, Final

# Function codes that write (FC23 reads too, but its write is what matters here).
WRITE_FUNCTIONS: Final = frozenset({5, 6, 15, 16, 23})
WINDOW_S: Final = 10.0  # a key written on and on: one record per window
MAX_KEYS: Final = 256
MAX_KEYS_PER_PEER: Final = 64  # one peer cannot push the others' writes out of itemized records
PEERS_NAMED: Final = 8  # in a record of writes beyond the keys

Key = tuple[str, int, int, int | None, int, int]


def describe_write(pdu: bytes) -> dict[str, Any]:
    """What a write request asks, for the audit trail: function, table, 0-based address and
    the values (bits 0/1 or registers; the trail keeps the first 32). A malformed request
    is described by its function code (the slave answers it with an exception)."""
    function = pdu[0]
    body = pdu[1:]
    try:
        if function in (5, 6):
            address, value = struct.unpack(">HH", body)
            values = [int(value == 0xFF00)] if function == 5 else [value]
        elif function in (15, 16):
            address, count, size = struct.unpack_from(">HHB", body)
            values = _values(function, body[5:5 + size], count)
        elif function == 23:
            address, count, size = struct.unpack_from(">HHB", body, 4)
            values = _values(16, body[9:9 + size], count)
        else:
            return {"function": function}
    except struct.error:
        return {"function": function, "malformed": True}
    table = "coils" if function in (5, 15) else "holding registers"
    return {"function": function, "table": table, "address": address, "values": values}


def _values(function: int, data: bytes, count: int) -> list[int]:
    if function == 15:
        return [(data[i // 8] >> (i % 8)) & 1 for i in range(min(count, 8 * len(data)))]
    return list(struct.unpack(f">{len(data) // 2}H", data[:len(data) // 2 * 2]))[:count]


def outcome_of(code: int) -> str:
    """The audit outcome of a write answered with exception `code` (0: none)."""
    return "applied" if code == 0 else "refused"


def utc_text(wall_s: float) -> str:
    """A wall-clock time as the trail writes its own (`time`): UTC, milliseconds."""
    when = datetime.datetime.fromtimestamp(wall_s, datetime.UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


@dataclass(slots=True)
class _Window:
    """The writes of one key counted since its last record."""

    entry: dict[str, Any]  # who and what, without the counts
    ends_s: float
    values: Any  # of the last write: `changed` compares with it
    writes: int = 0
    changed: int = 0
    first_s: float = 0.0
    last_s: float = 0.0

    def count(self, values: Any, now_s: float) -> None:
        if self.writes == 0:
            self.first_s = now_s
        self.writes += 1
        self.changed += values != self.values
        self.values, self.last_s = values, now_s

    def summary(self, now_s: float, wall_s: float) -> dict[str, Any]:
        detail = {**self.entry["detail"], "writes": self.writes, "changed": self.changed,
                  "first": utc_text(wall_s - (now_s - self.first_s)),
                  "last": utc_text(wall_s - (now_s - self.last_s))}
        if self.values is not None:
            detail["values"] = self.values
        return {**self.entry, "detail": detail}


@dataclass(slots=True)
class _Beyond:
    """Writes of keys that found no room, per outcome, since their last record."""

    entry: dict[str, Any]
    ends_s: float
    writes: int = 0
    peers: list[str] = field(default_factory=list)
    more_peers: int = 0
    first_s: float = 0.0
    last_s: float = 0.0

    def count(self, peer: str, now_s: float) -> None:
        if self.writes == 0:
            self.first_s = now_s
        self.writes += 1
        self.last_s = now_s
        if peer not in self.peers:
            if len(self.peers) < PEERS_NAMED:
                self.peers.append(peer)
            else:
                self.more_peers += 1

    def summary(self, now_s: float, wall_s: float) -> dict[str, Any]:
        detail = {**self.entry["detail"], "writes": self.writes, "peers": self.peers,
                  "more_peers": self.more_peers,
                  "first": utc_text(wall_s - (now_s - self.first_s)),
                  "last": utc_text(wall_s - (now_s - self.last_s))}
        return {**self.entry, "peer": self.peers[0], "detail": detail}


class Coalescer:
    """The audit records of one slave's writes. `who` (user, role, via) and `context` (added
    to every detail: the write policy) are the same for every write."""

    def __init__(self, who: dict[str, Any], context: dict[str, Any] | None = None, *,
                 window_s: float = WINDOW_S, max_keys: int = MAX_KEYS,
                 max_keys_per_peer: int = MAX_KEYS_PER_PEER) -> None:
        self._who = who
        self._context = context or {}
        self.window_s = window_s
        self._max_keys = max_keys
        self._max_per_peer = max_keys_per_peer
        self._open: dict[Key, _Window] = {}
        self._per_peer: dict[str, int] = {}
        self._beyond: dict[int, _Beyond] = {}

    @property
    def open(self) -> int:
        """Windows open (a timer must call `due` while there are any)."""
        return len(self._open) + len(self._beyond)

    def note(self, peer: str, unit: int, described: dict[str, Any], code: int, now_s: float,
             record_now: bool = True) -> dict[str, Any] | None:
        """One write (`described` by describe_write, answered with exception `code`, 0 for
        none): the record to write now, or None when it is counted for a later one.
        `record_now` False (the writer lags): even a first write is only counted."""
        values = described.get("values")
        key = (peer, unit, int(described["function"]), described.get("address"),
               len(values) if isinstance(values, list) else 0, code)
        window = self._open.get(key)
        if window is not None:
            window.count(values, now_s)
            return None
        if len(self._open) >= self._max_keys or \
                self._per_peer.get(peer, 0) >= self._max_per_peer:
            self._count_beyond(peer, code, now_s)
            return None
        detail = {**described, "unit": unit, **self._context}
        entry = {**self._who, "peer": peer, "iface": "modbus", "action": "write",
                 "outcome": outcome_of(code), "status": code, "detail": detail}
        window = self._open[key] = _Window(entry, now_s + self.window_s, values)
        self._per_peer[peer] = self._per_peer.get(peer, 0) + 1
        if not record_now:
            window.count(values, now_s)
            return None
        return {**entry, "detail": {**detail, "writes": 1}}

    def _count_beyond(self, peer: str, code: int, now_s: float) -> None:
        beyond = self._beyond.get(code)
        if beyond is None:
            detail = {"beyond_keys": self._max_keys, "beyond_keys_per_peer": self._max_per_peer,
                      **self._context}
            entry = {**self._who, "peer": peer, "iface": "modbus", "action": "write",
                     "outcome": outcome_of(code), "status": code, "detail": detail}
            beyond = self._beyond[code] = _Beyond(entry, now_s + self.window_s)
        beyond.count(peer, now_s)

    def due(self, now_s: float, wall_s: float) -> list[dict[str, Any]]:
        """The records of the windows closed by `now_s` (`wall_s`: the wall clock then)."""
        records: list[dict[str, Any]] = []
        for key, window in list(self._open.items()):
            if window.ends_s > now_s:
                continue
            if window.writes:
                records.append(window.summary(now_s, wall_s))
                window.writes = window.changed = 0
                window.ends_s = now_s + self.window_s
            else:
                self._forget(key)
        for code, beyond in list(self._beyond.items()):
            if beyond.ends_s <= now_s:
                records.append(beyond.summary(now_s, wall_s))
                del self._beyond[code]
        return records

    def drain(self, now_s: float, wall_s: float) -> list[dict[str, Any]]:
        """Every count not recorded yet, as records (at stop); nothing stays open."""
        records = [w.summary(now_s, wall_s) for w in self._open.values() if w.writes]
        records += [b.summary(now_s, wall_s) for b in self._beyond.values()]
        self._open.clear()
        self._per_peer.clear()
        self._beyond.clear()
        return records

    def _forget(self, key: Key) -> None:
        del self._open[key]
        peer = key[0]
        left = self._per_peer[peer] - 1
        if left:
            self._per_peer[peer] = left
        else:
            del self._per_peer[peer]
