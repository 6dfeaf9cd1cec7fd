"""The audit trail: append-only, hash-chained JSON lines in STATE_DIR/audit.jsonl.

Owns: the record format (canonical JSON: sorted keys, no spaces, ASCII; `seq` counting up
across files, `time` UTC, `prev` = the previous record's `hash`, `hash` = SHA-256 of the
record without it), appending from several processes (flock on STATE_DIR/audit.lock around
read-last-hash + append + fsync), rotation bounded in size (audit.jsonl -> audit.1.jsonl ->
... -> audit.KEEP.jsonl, then dropped; the chain and `seq` go on across files), reading,
verifying (auditchain.py: any changed byte breaks its record's hash or the next record's
`prev`; a verification can go on from where the last one ended; the head file and the
writer's last record must be there), a break record first when an append finds the trail
cut or rewritten (auditbreak.py), and following it as records come (`Follower`: for the
admin's event stream).
Does not know: HTTP, users, who calls it. Every call is blocking file I/O.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import fcntl
import hashlib
import json
import logging
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Final

from softplc.core.units import parse_duration_ns
from softplc.security.auditbreak import (
    HEAD_FILE,
    HeadUnreadable,
    find_break,
    hash_of,
    read_head,
    write_head,
)
from softplc.security.auditchain import GENESIS as GENESIS
from softplc.security.auditchain import Anchor, Resume, verify_files, verify_tail
from softplc.security.auditchain import Verdict as Verdict
from softplc.security.auditchain import canonical as canonical

AUDIT_FILE: Final = "audit.jsonl"
LOCK_FILE: Final = "audit.lock"
MAX_BYTES: Final = 1 << 20  # per file; with KEEP old files at most ~9 MiB in all
KEEP: Final = 8
_TAIL_BYTES: Final = 65536
_TEXT_MAX: Final = 300  # a string in a record (a message, a symbol name) is cut here

log = logging.getLogger(__name__)


def utc_text(wall_s: float) -> str:
    """A wall-clock time as the trail writes its own (`time`): UTC, milliseconds."""
    when = datetime.datetime.fromtimestamp(wall_s, datetime.UTC)
    return when.strftime("%Y-%m-%dT%H:%M:%S.") + f"{when.microsecond // 1000:03d}Z"


def utc_now() -> str:
    return utc_text(time.time())


def parse_since(text: str, now: datetime.datetime | None = None) -> str:
    """A time to compare record times with: ISO 8601 (`2025-03-01`, `2025-03-01T08:00`,
    with Z or an offset; no zone is UTC) or a duration back from now (`90s`, `2h`)."""
    now = now or datetime.datetime.now(datetime.UTC)
    try:
        when = now - datetime.timedelta(microseconds=parse_duration_ns(text) / 1000)
    except ValueError:
        try:
            when = datetime.datetime.fromisoformat(text.strip().replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"--since {text!r}: an ISO time (2025-03-01T08:00Z) or a "
                             "duration back from now (2h, 30min)") from None
        if when.tzinfo is None:
            when = when.replace(tzinfo=datetime.UTC)
    return when.astimezone(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"


def _clip(value: Any) -> Any:
    if isinstance(value, str):
        return value[:_TEXT_MAX]
    if isinstance(value, dict):
        return {str(k)[:_TEXT_MAX]: _clip(v) for k, v in list(value.items())[:32]}
    if isinstance(value, list | tuple):
        return [_clip(v) for v in value[:32]]
    return value if isinstance(value, int | bool) or value is None else str(value)[:_TEXT_MAX]


class AuditTrail:
    """The trail of one state directory, as one writer appends to it: the last record this
    object wrote (`known`) must still be there at its next append, as must the one the head
    file names (written by whichever process appended last)."""

    def __init__(self, state_dir: Path | str, max_bytes: int = MAX_BYTES,
                 keep: int = KEEP) -> None:
        self.dir = Path(state_dir)
        self.path = self.dir / AUDIT_FILE
        self.head = self.dir / HEAD_FILE
        self.max_bytes = max_bytes
        self.keep = keep
        self.known: Anchor | None = None

    def files(self) -> list[Path]:
        """Oldest first."""
        rotated = [self._rotated(n) for n in range(self.keep, 0, -1)]
        return [p for p in [*rotated, self.path] if p.exists()]

    def _rotated(self, n: int) -> Path:
        return self.dir / f"audit.{n}.jsonl"

    def append(self, entry: dict[str, Any]) -> dict[str, Any]:
        """Add one record (who, what, outcome: the caller's keys) and return it as written.
        When the trail no longer holds what this writer or the head file knows was written,
        a break record saying so is chained on first (auditbreak.py)."""
        self.dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        lock = os.open(self.dir / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
            last = self._last()
            found = find_break(self.known, self.head, last,
                               lambda seq: hash_of(self.files(), seq), entry.get("iface"))
            if self.path.exists() and self.path.stat().st_size >= self.max_bytes:
                self._rotate()
            if found is not None:
                log.error("audit trail %s: %s; a break record is written", self.path,
                          found["detail"]["problem"])
                last = _anchor(self._write(found, last))
            record = self._write({k: v for k, v in entry.items() if k != "break"}, last)
            self.known = _anchor(record)
            try:
                write_head(self.head, self.known)
            except OSError as exc:  # the next append finds an older head: still in the trail
                log.warning("audit trail head %s not written: %s", self.head, exc)
            return record
        finally:
            os.close(lock)

    def _write(self, entry: dict[str, Any], last: Anchor) -> dict[str, Any]:
        record = {**_clip(entry), "seq": last[0] + 1, "time": utc_now(), "prev": last[1]}
        record["hash"] = hashlib.sha256(canonical(record).encode()).hexdigest()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o600)
        try:
            os.write(fd, (canonical(record) + "\n").encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        return record

    def _rotate(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self._rotated(self.keep).unlink()
        for n in range(self.keep - 1, 0, -1):
            with contextlib.suppress(FileNotFoundError):
                self._rotated(n).rename(self._rotated(n + 1))
        self.path.rename(self._rotated(1))

    def _last(self) -> Anchor:
        """The newest record's seq and hash, from the tail of the newest non-empty file."""
        for path in reversed(self.files()):
            with path.open("rb") as handle:
                size = handle.seek(0, os.SEEK_END)
                handle.seek(max(0, size - _TAIL_BYTES))
                lines = handle.read().splitlines()
            for raw in reversed(lines):
                with contextlib.suppress(ValueError, AttributeError, TypeError, KeyError):
                    return _anchor(json.loads(raw))
        return 0, GENESIS

    def lines(self) -> Iterator[tuple[str, int, bytes]]:
        """(file name, line number, raw line) of every record, oldest first."""
        for path in self.files():
            with path.open("rb") as handle:
                for number, raw in enumerate(handle, 1):
                    yield path.name, number, raw.rstrip(b"\n")

    def records(self, since: str | None = None, limit: int | None = None
                ) -> list[dict[str, Any]]:
        """Records at or after `since` (parse_since's form), the newest `limit` of them; a
        line that is not a record comes back as {"unreadable": "FILE:LINE"}."""
        found: list[dict[str, Any]] = []
        for name, number, raw in self.lines():
            try:
                record = json.loads(raw)
                if not isinstance(record, dict):
                    raise ValueError("not an object")
            except ValueError:
                found.append({"unreadable": f"{name}:{number}"})
                continue
            if since is None or str(record.get("time", "")) >= since:
                found.append(record)
        return found[-limit:] if limit else found

    def verify(self, anchor: Anchor | None = None) -> Verdict:
        """Check every record and the links between them (auditchain.py). `anchor` (seq,
        hash), a record known to have been written (a running server keeps its last one),
        and the record the head file names must still be there: a trail rewritten from
        before them, or cut short, fails; so does a break record in it."""
        # The head first: read after the files, it could name a record appended since.
        try:
            anchors, unreadable = self._anchors(anchor), None
        except HeadUnreadable as exc:
            anchors, unreadable = tuple(a for a in (anchor,) if a is not None), str(exc)
        verdict = verify_files(self.files(), self.keep, anchors, self.path.name)
        if unreadable is None or not verdict.ok:
            return verdict
        return dataclasses.replace(verdict, ok=False, where=self.head.name, resume=None,
                                   problem=f"unreadable ({unreadable}): the next record "
                                   "appended records a break of the trail")

    def verify_tail(self, resume: Resume, anchor: Anchor | None = None) -> Verdict | None:
        """Go on from an earlier verdict's `resume`: the bytes verified then hashed again,
        only the records appended since parsed; None when a full verification is due."""
        try:
            anchors = self._anchors(anchor)
        except HeadUnreadable:
            return None
        return verify_tail(resume, self.files(), anchors, self.path.name)

    def _anchors(self, anchor: Anchor | None) -> tuple[Anchor, ...]:
        head = read_head(self.head)
        return tuple(a for a in (anchor, head) if a is not None)


class Follower:
    """The records appended to a trail after seq `after` (None: its newest), as they come,
    by whichever process: the newest file's inode and how far it was read are kept, so a
    poll that finds nothing new costs one stat; after a rotation (another inode) the files
    are searched again from `after`. Blocking file I/O, like the rest of this module."""

    def __init__(self, trail: AuditTrail, after: int | None = None) -> None:
        self.trail = trail
        self.after = trail._last()[0] if after is None else after
        self._inode: int | None = None
        self._offset = 0

    def poll(self, limit: int) -> tuple[list[dict[str, Any]], int]:
        """The new records, the newest `limit` of them, and how many were skipped (beyond
        `limit`, or gone with files rotated away before they were read)."""
        try:
            info = self.trail.path.stat()
        except FileNotFoundError:  # none yet, or between a rotation and the next record
            return [], 0
        if info.st_ino == self._inode and info.st_size == self._offset:
            return [], 0
        raws = self._grown() if info.st_ino == self._inode and info.st_size > self._offset \
            else None
        found = [r for r in map(_record, self._search() if raws is None else raws)
                 if r is not None and r["seq"] > self.after]
        skipped = found[0]["seq"] - self.after - 1 if found else 0
        if len(found) > limit:
            skipped, found = skipped + len(found) - limit, found[-limit:]
        if found:
            self.after = found[-1]["seq"]
        return found, max(0, skipped)

    def _grown(self) -> list[bytes] | None:
        """The lines appended to the file read last; None when the path is another file."""
        with self.trail.path.open("rb") as handle:
            if os.fstat(handle.fileno()).st_ino != self._inode:
                return None
            handle.seek(self._offset)
            return self._whole_lines(handle.read())

    def _whole_lines(self, data: bytes) -> list[bytes]:
        # A line being appended (no newline yet) is read at the next poll.
        end = data.rfind(b"\n") + 1
        self._offset += end
        return data[:end].splitlines()

    def _search(self) -> list[bytes]:
        """The lines of every file from the newest one that starts at or before `after`+1;
        the newest file is remembered to be read on from where it ends."""
        files = self.trail.files()
        start = 0
        for index in range(len(files) - 1, -1, -1):
            first = _first_seq(files[index])
            if first is not None and first <= self.after + 1:
                start = index
                break
        lines: list[bytes] = []
        for path in files[start:]:
            with contextlib.suppress(FileNotFoundError), path.open("rb") as handle:
                if path == self.trail.path:
                    self._inode, self._offset = os.fstat(handle.fileno()).st_ino, 0
                    lines += self._whole_lines(handle.read())
                else:
                    lines += handle.read().splitlines()
        newest = next((r["seq"] for r in map(_record, reversed(lines)) if r is not None), 0)
        if newest < self.after:  # the trail was cut or replaced: follow the one there is
            self.after = 0
        return lines


def _anchor(record: dict[str, Any]) -> Anchor:
    return int(record["seq"]), str(record["hash"])


def _record(raw: bytes) -> dict[str, Any] | None:
    with contextlib.suppress(ValueError):
        record = json.loads(raw)
        if isinstance(record, dict) and isinstance(record.get("seq"), int):
            return record
    return None


def _first_seq(path: Path) -> int | None:
    with contextlib.suppress(OSError), path.open("rb") as handle:
        record = _record(handle.readline())
        return None if record is None else int(record["seq"])
    return None
