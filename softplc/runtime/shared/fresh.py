"""How old the published snapshot is, as the communication side sees it.

Owns: the stale verdict (the scan process has not published for STALE_PERIODS periods, and at
least STALE_MIN_NS), stamped into every snapshot the Modbus slave, the API and OPC UA serve.
Does not know: what is served, or why the scan process is late (paused, starved, dead,
restarting: all look the same from here, and all mean the values are old).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Final

from softplc.core.snapshot import Snapshot, SnapshotSource, age_ns

STALE_PERIODS: Final = 5
STALE_MIN_NS: Final = 200_000_000  # below this, a busy 2-core machine's jitter would flag


def stale_after_ns(period_us: int) -> int:
    return max(STALE_PERIODS * period_us * 1000, STALE_MIN_NS)


class FreshSource:
    """A SnapshotSource whose snapshots say whether they are stale (Status.stale)."""

    def __init__(self, source: SnapshotSource) -> None:
        self._source = source

    def latest(self) -> Snapshot:
        snapshot = self._source.latest()
        status = snapshot.status
        if status.published_ns and self.age_ns(snapshot) <= stale_after_ns(status.period_us):
            return snapshot
        return dataclasses.replace(snapshot, status=dataclasses.replace(status, stale=True))

    @staticmethod
    def age_ns(snapshot: Snapshot) -> int:
        """Nanoseconds since the scan process published `snapshot` (machine-wide clock)."""
        return age_ns(snapshot, time.monotonic_ns())
