"""The back-off of failed logins, one rule for every interface (HTTP, the page, OPC UA).

Owns: how long a user name or a peer address is closed after failed logins, in a bounded
table. Pure: imports nothing of HTTP or OPC UA, so the OPC UA process (which must not pay for
aiohttp's import) uses the same rule as the HTTP one.
Does not know: passwords, users, sockets.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Final

FREE_FAILURES: Final = 3  # failed logins before the back-off starts
BACKOFF_BASE_S: Final = 1.0  # doubles with each further failure
BACKOFF_MAX_S: Final = 60.0
BACKOFF_ENTRIES: Final = 4096  # users and peers remembered; the least recent go first


class Backoff:
    """Failures per key (("user", name) or ("peer", address)): after FREE_FAILURES, each
    further one closes that key for BACKOFF_BASE_S x 2**k, at most BACKOFF_MAX_S; a success
    clears it. At most BACKOFF_ENTRIES keys: an address flood evicts the oldest, it does not
    grow the table."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._table: OrderedDict[tuple[str, str], tuple[int, float]] = OrderedDict()

    def wait_s(self, *keys: tuple[str, str]) -> float:
        now = self._clock()
        return max([self._table.get(k, (0, now))[1] - now for k in keys] + [0.0])

    def failed(self, *keys: tuple[str, str]) -> None:
        now = self._clock()
        for key in keys:
            count = self._table.pop(key, (0, now))[0] + 1
            delay = 0.0 if count <= FREE_FAILURES else min(
                BACKOFF_BASE_S * 2 ** (count - FREE_FAILURES - 1), BACKOFF_MAX_S)
            self._table[key] = (count, now + delay)
            while len(self._table) > BACKOFF_ENTRIES:
                self._table.popitem(last=False)

    def succeeded(self, *keys: tuple[str, str]) -> None:
        for key in keys:
            self._table.pop(key, None)
