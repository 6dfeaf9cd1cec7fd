"""A scan that never ends still faults: a thread of the scan process that watches the scan
thread and acts for it when one scan has run longer than the watchdog's hard limit (a driver
read that blocks forever, a runaway program). docs/faults.md, the watchdog.

Owns: HangWatch (the scan thread stamps where a scan begins and ends; the watching thread,
woken every quarter of the limit (at most 250 ms), calls back once per stuck scan; one lock
keeps its callback and the scan thread's next steps apart). Not started on a virtual clock
(tests, simulation): a scan cannot hang in time that does not pass.
Does not know: the PLC, its devices and status (the callback, ScanLoop._hung, acts).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Final

POLL_MAX_NS: Final = 250_000_000


class HangWatch:
    """`begin(now_ns)` when a scan starts and `end()` when it is done, on the scan thread,
    `now_ns` read off `clock`, the loop's own (after a warm start it continues the snapshot's
    time, behind the host's monotonic clock by the downtime: compared with the raw monotonic
    clock, every scan would look as old as the downtime). A scan still running `limit_ns` after its
    begin is found within `poll_s` more and `on_hang(elapsed_ns)` runs once, under `lock`, on
    the watching thread. `end()` takes the same lock, so the scan thread goes on only after
    the callback, and says whether it ran during this scan."""

    def __init__(self, limit_ns: int, on_hang: Callable[[int], None],
                 clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.limit_ns = limit_ns
        self.clock = clock
        self.poll_s = min(limit_ns // 4, POLL_MAX_NS) / 1e9
        self.on_hang = on_hang
        self.lock = threading.Lock()
        self.hangs = 0
        self._began_ns = 0  # 0: no scan in progress
        self._tripped = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="scan-watchdog", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)  # the callback is bounded by go_safe's own bound

    def begin(self, now_ns: int) -> None:
        self._began_ns = now_ns  # one store: all the scan thread pays per scan, with end()

    def end(self) -> bool:
        """The scan is over; True if on_hang ran for it."""
        with self.lock:
            self._began_ns = 0
            tripped, self._tripped = self._tripped, False
        return tripped

    def _watch(self) -> None:
        while not self._stop.wait(self.poll_s):
            self._watch_once()

    def _watch_once(self) -> None:
        began = self._began_ns
        if began and self.clock() - began > self.limit_ns:
            self._trip(began)

    def _trip(self, began: int) -> None:
        with self.lock:
            if self._began_ns != began or self._tripped:
                return  # ended meanwhile, or already reported
            self._tripped = True
            self.hangs += 1
            try:
                self.on_hang(self.clock() - began)
            except Exception as exc:  # the watching thread must outlive a failed callback
                print(f"softplc: scan watchdog: {type(exc).__name__}: {exc}", file=sys.stderr,
                      flush=True)
