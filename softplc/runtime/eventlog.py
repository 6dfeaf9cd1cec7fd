"""The scan process's event stream: what happened, numbered, for the status board.

Owns: the recent events (the last 256, each with its sequence number, scan and scan time)
and which of the engine's run-time diagnostics are put on the stream (a few per scan: a
guard failing every scan must not flood it; status counts them all).
Does not know: the scan loop, the board's transport, HTTP or OPC UA (which read the events
from the board).
"""

from __future__ import annotations

from collections import deque
from typing import Any

from softplc.core.engine import Engine

DIAGNOSTICS_PER_SCAN = 3


class EventLog:
    def __init__(self, seq: int = 0) -> None:
        self.events: deque[dict[str, Any]] = deque(maxlen=256)
        self.seq = seq  # the last number given: a restarted scan process goes on from its
        # predecessor's, so a client's "events since N" holds (docs/opcua.md, LastEventSeq)
        self._engine: Engine | None = None  # the engine whose diagnostics are counted
        self._seen = 0

    def add(self, name: str, scan: int, now_ns: int) -> None:
        self.seq += 1
        self.events.append({"seq": self.seq, "scan": scan, "t_ns": now_ns, "name": name})

    def diagnostics(self, engine: Engine | None, scan: int, now_ns: int) -> None:
        """The engine's new run-time diagnostics, at most DIAGNOSTICS_PER_SCAN of them."""
        if engine is None:
            return
        if engine is not self._engine:
            self._engine, self._seen = engine, 0
        if engine.diagnostic_count > self._seen:
            for message in engine.diagnostics[self._seen:self._seen + DIAGNOSTICS_PER_SCAN]:
                self.add(f"diagnostic:{message}", scan, now_ns)
            self._seen = engine.diagnostic_count


def newest_seq(document: dict[str, Any]) -> int:
    """The highest event number a status board `document` shows (0: none)."""
    return max((int(e["seq"]) for e in document.get("events") or []
                if isinstance(e, dict) and isinstance(e.get("seq"), int)), default=0)
