"""The audit chain's verdict for status, kept up to date without status waiting for it.

Owns: the last verdict and when it was computed (`checked_at`, UTC; `ok` null until the
first check has ended), and the next check, in a thread, at most every `interval_s` when a
file of the trail changed (name, inode, size, ctime) or the server wrote another record (its
anchor), and at least every REHASH_S while the verdict is good: from where the last good
verification ended (audit.py's `verify_tail`: the verified bytes hashed again, only the
appended records parsed; measured on a full trail of 9 MiB, ~24,000 records: ~10 ms against
~0.55 s for a full verification), or over the whole trail when that cannot be (a rotation,
a file rewritten, cut or changed in place). A break record in the trail (a writer found it
cut or rewritten, auditbreak.py) keeps `ok` false, named in `breaks`, while the checks still
go on from where the last one ended.
Does not know: HTTP, the chain's rules (auditchain.py), who writes the trail.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from typing import Any, Final

from softplc.security.audit import AuditTrail, utc_now
from softplc.security.auditchain import Resume, Verdict

log = logging.getLogger(__name__)

CHAIN_CHECK_S: Final = 5.0  # a trail that changes is checked again at most this often
# A good verdict is checked again after this even when no file seems changed: a write in
# place within the same clock tick as the last append leaves inode, size and ctime alone.
REHASH_S: Final = 60.0
UNCHECKED: Final[dict[str, Any]] = {"ok": None, "records": 0, "first_seq": 0, "last_seq": 0,
                                    "last_hash": None, "where": None, "problem": None,
                                    "breaks": []}

Anchor = tuple[int, str]


class ChainWatch:
    """The verdict of one trail for one server; call from its loop."""

    def __init__(self, trail: AuditTrail, interval_s: float = CHAIN_CHECK_S) -> None:
        self.trail = trail
        self.interval_s = interval_s
        self.full_checks = 0  # verifications of the whole trail
        self.parsed = 0  # lines read as JSON by every check: what checks cost
        self._verdict: dict[str, Any] = UNCHECKED
        self._checked_at: str | None = None
        self._checked_s = -math.inf  # loop time of the last check that verified
        self._stamp: object = None
        self._resume: Resume | None = None
        self._started_s = -math.inf
        self._task: asyncio.Task[None] | None = None

    def verdict(self, anchor: Anchor | None) -> dict[str, Any]:
        """The last verdict, at once; a check started when one may be due."""
        loop = asyncio.get_running_loop()
        if self._task is None and loop.time() - self._started_s >= self.interval_s:
            self._started_s = loop.time()
            self._task = loop.create_task(self._check(anchor))
        return {**self._verdict, "checked_at": self._checked_at}

    async def _check(self, anchor: Anchor | None) -> None:
        loop = asyncio.get_running_loop()
        # Unchanged files need no check, unless the verdict is none yet or a good one old.
        ok = self._verdict["ok"]
        skip = ok is False or (ok is True and loop.time() - self._checked_s < REHASH_S)
        try:
            stamp, verdict, full = await asyncio.to_thread(
                self._run, self._resume, self._stamp if skip else None, anchor)
        except OSError as exc:  # a file rotated away under the check: the next one sees
            log.warning("audit chain not checked: %s", exc)
            return
        finally:
            self._task = None
        if verdict is None:
            return
        self._stamp, self._resume = stamp, verdict.resume
        self._verdict, self._checked_at = verdict.as_dict(), utc_now()
        self._checked_s = loop.time()
        self.full_checks += full
        self.parsed += verdict.parsed

    def _run(self, resume: Resume | None, unchanged: object, anchor: Anchor | None
             ) -> tuple[object, Verdict | None, bool]:
        """In a thread: the files' stamp, and their verdict unless it equals `unchanged`;
        whether it took a full verification."""
        stamp = (self._files(), anchor)
        if stamp == unchanged:
            return stamp, None, False
        verdict = None if resume is None else self.trail.verify_tail(resume, anchor)
        if verdict is not None:
            return stamp, verdict, False
        return stamp, self.trail.verify(anchor), True

    def _files(self) -> tuple[tuple[str, int, int, int], ...]:
        stamps = []
        for path in self.trail.files():
            with contextlib.suppress(OSError):
                info = path.stat()
                stamps.append((path.name, info.st_ino, info.st_size, info.st_ctime_ns))
        return tuple(stamps)

    def close(self) -> None:
        """No verdict taken after this (a check under way finishes in its thread)."""
        if self._task is not None:
            self._task.cancel()
