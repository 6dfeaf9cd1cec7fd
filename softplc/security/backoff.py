"""The back-off of failed logins, one rule and one table for every door (HTTP, the page, OPC
UA), shared by the processes of one PLC.

Owns: how long a user name or a peer address is closed after failed logins, in a bounded
table kept in STATE_DIR/backoff.json (0600): read again at a check only when the file
changed (one stat otherwise), read, changed and replaced at each failure under a flock on
STATE_DIR/backoff.lock, so that failures at one door close the name at the others. Pure of
HTTP and OPC UA, so the OPC UA process (which must not pay for aiohttp's import) uses it too.
Does not know: passwords, users, sockets.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Final

FREE_FAILURES: Final = 3  # failed logins before the back-off starts
BACKOFF_BASE_S: Final = 1.0  # doubles with each further failure
BACKOFF_MAX_S: Final = 60.0
BACKOFF_ENTRIES: Final = 4096  # users and peers remembered; the least recent go first
# A key whose closure ended this long ago is forgotten: the table outlives restarts now.
BACKOFF_FORGET_S: Final = 3600.0
BACKOFF_FILE: Final = "backoff.json"
BACKOFF_LOCK: Final = "backoff.lock"

log = logging.getLogger(__name__)

Key = tuple[str, str]
Table = OrderedDict[Key, tuple[int, float]]  # key -> (failures, closed until: clock time)


class Backoff:
    """Failures per key (("user", name) or ("peer", address)): after FREE_FAILURES, each
    further one closes that key for BACKOFF_BASE_S x 2**k, at most BACKOFF_MAX_S; a success
    clears it. At most BACKOFF_ENTRIES keys: an address flood evicts the oldest, it does not
    grow the table. With `state_dir` the table is the file there, shared by every Backoff of
    that directory (the clock is then the wall clock, the same in every process; a wait is
    never longer than BACKOFF_MAX_S, whatever the clock did); without, this object's own."""

    def __init__(self, clock: Callable[[], float] = time.time,
                 state_dir: Path | str | None = None) -> None:
        self._clock = clock
        self._table: Table = OrderedDict()
        self._dir = None if state_dir is None else Path(state_dir)
        self._stamp: tuple[int, int, int] | None = None  # the file as last read or written
        self._said: set[str] = set()  # problems logged once

    @property
    def path(self) -> Path | None:
        return None if self._dir is None else self._dir / BACKOFF_FILE

    def wait_s(self, *keys: Key) -> float:
        self._refresh()
        now = self._clock()
        waits = [self._table.get(k, (0, now))[1] - now for k in keys]
        return min(max([*waits, 0.0]), BACKOFF_MAX_S)

    def failed(self, *keys: Key) -> None:
        with self._locked():
            now = self._clock()
            for key in keys:
                count = self._table.pop(key, (0, now))[0] + 1
                delay = 0.0 if count <= FREE_FAILURES else min(
                    BACKOFF_BASE_S * 2 ** (count - FREE_FAILURES - 1), BACKOFF_MAX_S)
                self._table[key] = (count, now + delay)
            while len(self._table) > BACKOFF_ENTRIES:
                self._table.popitem(last=False)

    def succeeded(self, *keys: Key) -> None:
        self._refresh()
        if not any(k in self._table for k in keys):  # the common case: no write
            return
        with self._locked():
            for key in keys:
                self._table.pop(key, None)

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """The table read fresh, changed by the caller, then written back, the file's lock
        held; without a file (or a lock that cannot be had), this object's table alone."""
        if self._dir is None:
            yield
            return
        try:
            self._dir.mkdir(parents=True, exist_ok=True, mode=0o700)
            lock = os.open(self._dir / BACKOFF_LOCK, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            self._say(f"back-off table {self._dir / BACKOFF_LOCK} not shared ({exc.strerror}): "
                      "this process counts alone")
            yield
            return
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
            self._refresh()
            yield
            self._store(self._dir / BACKOFF_FILE)
        finally:
            os.close(lock)

    def _refresh(self) -> None:
        """Read the file again when it is not the one read last (one stat when it is)."""
        path = self.path
        if path is None:
            return
        try:
            info = path.stat()
        except FileNotFoundError:
            if self._stamp is not None:  # removed: every closure lifted
                self._table.clear()
                self._stamp = None
            return
        except OSError as exc:
            self._say(f"back-off table {path} unreadable ({exc.strerror}): this process "
                      "counts alone")
            return
        stamp = (info.st_ino, info.st_mtime_ns, info.st_size)
        if stamp == self._stamp:
            return
        self._stamp = stamp
        try:
            self._table = _parse(path.read_bytes(), self._clock())
        except (OSError, ValueError, TypeError, KeyError) as exc:
            # Back-off only slows a guesser: an empty table is safe, a dead service is not.
            self._say(f"back-off table {path} unreadable ({exc}): starting from an empty one")
            self._table = OrderedDict()

    def _store(self, path: Path) -> None:
        now = self._clock()
        for key in [k for k, (_, until) in self._table.items() if until + BACKOFF_FORGET_S < now]:
            del self._table[key]
        rows = [[kind, name, count, until] for (kind, name), (count, until)
                in self._table.items()]
        temporary = path.with_name(path.name + ".tmp")
        try:
            fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                os.write(fd, json.dumps({"entries": rows}, separators=(",", ":")).encode())
            finally:
                os.close(fd)
            os.replace(temporary, path)
            info = path.stat()
        except OSError as exc:
            self._say(f"back-off table {path} not written ({exc.strerror}): this process "
                      "counts alone")
            return
        self._stamp = (info.st_ino, info.st_mtime_ns, info.st_size)

    def _say(self, problem: str) -> None:
        if problem not in self._said:
            self._said.add(problem)
            log.warning("%s", problem)


def _parse(raw: bytes, now: float) -> Table:
    """The file's table, oldest first, without keys forgotten by now; ValueError, TypeError
    or KeyError for anything else."""
    rows = json.loads(raw)["entries"]
    table: Table = OrderedDict()
    for kind, name, count, until in rows[-BACKOFF_ENTRIES:]:
        if not all(isinstance(v, str) for v in (kind, name)) or not isinstance(count, int) \
                or not isinstance(until, int | float):
            raise ValueError("not a back-off entry")
        if until + BACKOFF_FORGET_S >= now:
            table[(kind, name)] = (count, float(until))
    return table
