"""What a Modbus write asks, and the rule that bounds the audit records of many writes.

Owns: the function codes that write and the description of a write request (function,
table, 0-based address, values); `Coalescer`, the rule of docs/security.md ("Audit of plain
Modbus writes"): per key (peer, unit, function, address, quantity, outcome) the first write
is a record at once, and the writes that follow within `window_s` are counted into one
record at the window's close carrying how many, how often the value changed, the last value
and the times of the first and last; a key still written at the close opens the next window
without a record of its own, an idle one is forgotten. At most `max_keys` keys (and
`max_keys_per_peer` of one peer) are open: writes beyond are counted per outcome into one
record naming their peers. The windows themselves are core/repeats.py's (the HTTP gate's
refusals use the same rule: security/refusals.py); this module says what a write's key and
records are.
Does not know: sockets, clocks (times are arguments), the trail (records are returned).
"""

from __future__ import annotations

import datetime
import struct
from typing import Any, Final

from softplc.core.repeats import Repeats, Tally


def utc_text(wall_s: float) -> str:
    """A wall-clock time as the audit trail writes its own (`time`): UTC, milliseconds."""
    when = datetime.datetime.fromtimestamp(wall_s, datetime.UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"

# Function codes that write (FC23 reads too, but its write is what matters here).
WRITE_FUNCTIONS: Final = frozenset({5, 6, 15, 16, 23})
WINDOW_S: Final = 10.0  # a key written on and on: one record per window
MAX_KEYS: Final = 256
MAX_KEYS_PER_PEER: Final = 64  # one peer cannot push the others' writes out of itemized records

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


class Coalescer:
    """The audit records of one slave's writes. `who` (user, role, via) and `context` (added
    to every detail: the write policy) are the same for every write."""

    def __init__(self, who: dict[str, Any], context: dict[str, Any] | None = None, *,
                 window_s: float = WINDOW_S, max_keys: int = MAX_KEYS,
                 max_keys_per_peer: int = MAX_KEYS_PER_PEER) -> None:
        self._who = who
        self._context = context or {}
        self._max_keys = max_keys
        self._max_per_peer = max_keys_per_peer
        self._repeats: Repeats[Key] = Repeats(window_s, max_keys, max_keys_per_peer)

    @property
    def window_s(self) -> float:
        return self._repeats.window_s

    @property
    def open(self) -> int:
        """Windows open (a timer must call `due` while there are any)."""
        return self._repeats.open

    def note(self, peer: str, unit: int, described: dict[str, Any], code: int, now_s: float,
             record_now: bool = True) -> dict[str, Any] | None:
        """One write (`described` by describe_write, answered with exception `code`, 0 for
        none): the record to write now, or None when it is counted for a later one.
        `record_now` False (the writer lags): even a first write is only counted."""
        values = described.get("values")
        key = (peer, unit, int(described["function"]), described.get("address"),
               len(values) if isinstance(values, list) else 0, code)
        if self._repeats.again(key, now_s, values):
            return None
        detail = {**described, "unit": unit, **self._context}
        entry = {**self._who, "peer": peer, "iface": "modbus", "action": "write",
                 "outcome": outcome_of(code), "status": code, "detail": detail}
        if not self._repeats.first(key, peer, entry, now_s, values, counted=not record_now):
            self._repeats.beyond(code, peer, now_s, lambda: self._beyond_entry(peer, code))
            return None
        return {**entry, "detail": {**detail, "writes": 1}} if record_now else None

    def _beyond_entry(self, peer: str, code: int) -> dict[str, Any]:
        detail = {"beyond_keys": self._max_keys, "beyond_keys_per_peer": self._max_per_peer,
                  **self._context}
        return {**self._who, "peer": peer, "iface": "modbus", "action": "write",
                "outcome": outcome_of(code), "status": code, "detail": detail}

    def due(self, now_s: float, wall_s: float) -> list[dict[str, Any]]:
        """The records of the windows closed by `now_s` (`wall_s`: the wall clock then)."""
        return [_summary(t, now_s, wall_s) for t in self._repeats.due(now_s)]

    def drain(self, now_s: float, wall_s: float) -> list[dict[str, Any]]:
        """Every count not recorded yet, as records (at stop); nothing stays open."""
        return [_summary(t, now_s, wall_s) for t in self._repeats.drain()]


def _summary(tally: Tally, now_s: float, wall_s: float) -> dict[str, Any]:
    """The record of a window's writes: how many, how often the value changed, the last
    value; for writes beyond the keys, how many and whose."""
    entry = tally.entry
    if tally.beyond:
        return {**entry, "peer": tally.peers[0], "detail": {
            **entry["detail"], "writes": tally.count, "peers": tally.peers,
            "more_peers": tally.more_peers, **tally.times(now_s, wall_s, utc_text)}}
    detail = {**entry["detail"], "writes": tally.count, "changed": tally.changed,
              **tally.times(now_s, wall_s, utc_text)}
    if tally.payload is not None:
        detail["values"] = tally.payload
    return {**entry, "detail": detail}
