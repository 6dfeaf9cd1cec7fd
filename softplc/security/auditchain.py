"""The audit chain's verification, and going on from where the last one ended.

Owns: canonical form, GENESIS, Verdict, the check of one line after the record before it
(canonical form, its hash, `seq` and `prev`), `verify_files` (every line of the trail's
files, oldest first; anchors, records known to have been written, must be there; a break
record, written where a writer found the trail cut or rewritten, keeps the verdict bad) and
`verify_tail`: from where a verification ended (`Resume`: each file's inode, the bytes and
lines verified and their SHA-256, the chain after them) it re-hashes those bytes, a few ms
for a full trail where parsing its records costs ~0.5 s, and checks only the lines appended
since; None when a file was replaced, cut, rotated or changed in place (a full verification
is due then).
Does not know: where the trail is or how it is written (audit.py, auditbreak.py), HTTP.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

GENESIS: Final = "0" * 64  # `prev` of the first record ever
RECENT: Final = 256  # (seq, hash) of the newest records verified, for a late anchor

Anchor = tuple[int, str]
Break = tuple[str, str]  # a break record's FILE:LINE, and what it says


def canonical(record: dict[str, Any]) -> str:
    return json.dumps(record, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


@dataclass(frozen=True, slots=True)
class FileMark:
    """One file as verified: `size` bytes (whole lines), `lines` of them, their SHA-256."""

    name: str
    inode: int
    size: int
    lines: int
    digest: bytes


@dataclass(frozen=True, slots=True)
class Resume:
    """Where a verification that found the chain intact ended: the files and the chain's
    state after their last whole line."""

    files: tuple[FileMark, ...]
    count: int
    first: int
    seq: int
    last: str
    dropped: bool
    recent: tuple[Anchor, ...]
    anchors: tuple[Anchor, ...]  # the anchors found where they should be
    breaks: tuple[Break, ...]


@dataclass(frozen=True, slots=True)
class Verdict:
    """What a verification found: `ok`, how many records, the last seq and hash, and for a
    break the first bad record's position (`where`: FILE:LINE) and what is wrong with it.
    `breaks`: every break record (FILE:LINE, what was lost): the chain links, but
    evidence before it was cut or rewritten, so `ok` is false while one is in the trail.
    `parsed`: the lines this verification read as JSON; `resume`: where to go on from."""

    ok: bool
    records: int
    last_seq: int
    last_hash: str
    where: str | None = None
    problem: str | None = None
    first_seq: int = 0
    breaks: tuple[Break, ...] = ()
    parsed: int = field(default=0, compare=False)
    resume: Resume | None = field(default=None, compare=False, repr=False)

    def as_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "records": self.records, "first_seq": self.first_seq,
                "last_seq": self.last_seq, "last_hash": self.last_hash, "where": self.where,
                "problem": self.problem,
                "breaks": [{"where": where, "what": what} for where, what in self.breaks]}


class _Scan:
    """A verification under way: the chain up to the last line checked."""

    def __init__(self, anchors: Sequence[Anchor], dropped: bool) -> None:
        self.missing = list(dict.fromkeys(anchors))
        self.found: list[Anchor] = []
        self.breaks: list[Break] = []
        self.dropped = dropped
        self.count, self.first, self.seq, self.last = 0, 0, 0, GENESIS
        self.recent: deque[Anchor] = deque(maxlen=RECENT)
        self.parsed = 0
        self.broken: Verdict | None = None

    @classmethod
    def resumed(cls, resume: Resume, anchors: Sequence[Anchor]) -> _Scan:
        scan = cls(anchors, resume.dropped)
        scan.count, scan.first, scan.seq, scan.last = (resume.count, resume.first, resume.seq,
                                                       resume.last)
        scan.recent.extend(resume.recent)
        scan.found, scan.breaks = list(resume.anchors), list(resume.breaks)
        return scan

    def met(self, anchor: Anchor) -> None:
        """`anchor`, already verified before, found again."""
        if anchor in self.missing:
            self.missing.remove(anchor)
            self.found.append(anchor)

    def line(self, name: str, number: int, raw: bytes) -> bool:
        """Check one line; False (and `broken`) when it breaks the chain."""
        self.parsed += 1
        problem, record = _check(raw, self.seq, self.last, self.count == 0 and self.dropped)
        if problem is not None:
            self.broken = self._verdict(False, f"{name}:{number}", problem)
            return False
        self.count, self.seq, self.last = self.count + 1, record["seq"], record["hash"]
        self.first = self.first or self.seq
        self.recent.append((self.seq, self.last))
        for anchor in [a for a in self.missing if a[0] == self.seq]:
            if self.last != anchor[1]:
                self.broken = self._verdict(False, f"{name}:{number}", "this record is not the "
                                            f"one written as seq {self.seq}: the trail was "
                                            "rewritten")
                return False
            self.met(anchor)
        if record.get("break") is True:
            self.breaks.append((f"{name}:{number}", break_text(record)))
        return True

    def lines(self, name: str, data: bytes, start: int) -> bool:
        """Check the lines of `data`, numbered from `start`."""
        parts = data.split(b"\n")
        if parts[-1] == b"":
            parts.pop()
        return all(self.line(name, n, raw) for n, raw in enumerate(parts, start))

    def resume(self, files: tuple[FileMark, ...]) -> Resume:
        return Resume(files, self.count, self.first, self.seq, self.last, self.dropped,
                      tuple(self.recent), tuple(self.found), tuple(self.breaks))

    def end(self, newest: str, resume: Resume | None) -> Verdict:
        if self.broken is not None:
            return self.broken
        # An anchor older than the oldest record kept went with a rotated file.
        gone = [a for a in self.missing if a[0] >= self.first or not self.dropped]
        if gone:
            seq, digest = max(gone)
            return self._verdict(False, newest, f"record {seq} (hash {digest[:16]}), known to "
                                 f"have been written, is gone: the trail ends at seq "
                                 f"{self.seq}, it was cut")
        if self.breaks:
            where, text = self.breaks[0]
            return Verdict(False, self.count, self.seq, self.last, where,
                           f"a break of the trail is recorded here {text}", self.first,
                           tuple(self.breaks), parsed=self.parsed, resume=resume)
        return Verdict(True, self.count, self.seq, self.last, first_seq=self.first,
                       parsed=self.parsed, resume=resume)

    def _verdict(self, ok: bool, where: str, problem: str) -> Verdict:
        return Verdict(ok, self.count, self.seq, self.last, where, problem, self.first,
                       tuple(self.breaks), parsed=self.parsed)


def verify_files(paths: Sequence[Path], keep: int, anchors: Sequence[Anchor] = (),
                 newest: str = "audit.jsonl") -> Verdict:
    """Check every line of `paths` (oldest first; the last one is the file still written)."""
    # Only when every rotated slot is taken can older records have been dropped.
    scan = _Scan(anchors, len(paths) > keep)
    marks: list[FileMark] = []
    resume: Resume | None = None
    for index, path in enumerate(paths):
        with path.open("rb") as handle:
            inode = os.fstat(handle.fileno()).st_ino
            data = handle.read()
        last = index == len(paths) - 1
        whole = data.rfind(b"\n") + 1 if last else len(data)  # a line being appended waits
        marks.append(FileMark(path.name, inode, whole, _count_lines(data[:whole]),
                              hashlib.sha256(data[:whole]).digest()))
        if not scan.lines(path.name, data[:whole], 1):
            break
        if last:
            resume = scan.resume(tuple(marks))
            scan.lines(path.name, data[whole:], marks[-1].lines + 1)
    return scan.end(newest, resume)


def verify_tail(resume: Resume, paths: Sequence[Path], anchors: Sequence[Anchor] = (),
                newest: str = "audit.jsonl") -> Verdict | None:
    """Go on from `resume` over the same files: their verified bytes hashed again, the lines
    appended to the last one checked. None: a file is not the one verified (another inode,
    shorter, longer though rotated, other bytes): verify the whole trail instead."""
    if not paths or [p.name for p in paths] != [m.name for m in resume.files]:
        return None
    data = b""
    hasher = hashlib.sha256()
    for index, (path, mark) in enumerate(zip(paths, resume.files, strict=True)):
        last = index == len(paths) - 1
        with path.open("rb") as handle:
            if os.fstat(handle.fileno()).st_ino != mark.inode:
                return None
            data = handle.read() if last else handle.read(mark.size + 1)
        if len(data) < mark.size or (not last and len(data) != mark.size):
            return None
        hasher = hashlib.sha256(data[:mark.size])
        if hasher.digest() != mark.digest:
            return None
    scan = _Scan.resumed(resume, anchors)
    for anchor in anchors:
        if anchor[0] <= resume.seq:  # already verified, or a late anchor
            if anchor not in resume.anchors and anchor not in resume.recent:
                return None
            scan.met(anchor)
    mark = resume.files[-1]
    tail = data[mark.size:]
    whole = tail.rfind(b"\n") + 1
    if not scan.lines(mark.name, tail[:whole], mark.lines + 1):
        return scan.end(newest, None)
    hasher.update(tail[:whole])
    files = (*resume.files[:-1], FileMark(mark.name, mark.inode, mark.size + whole,
                                          mark.lines + _count_lines(tail[:whole]),
                                          hasher.digest()))
    after = scan.resume(files)
    scan.lines(mark.name, tail[whole:], files[-1].lines + 1)
    return scan.end(newest, after)


def break_text(record: dict[str, Any]) -> str:
    """What a break record says: (seq N) what was found, the last good record known."""
    detail = record.get("detail")
    detail = detail if isinstance(detail, dict) else {}
    good = str(detail.get("last_good_hash") or "")[:16] or "unknown"
    found = str(detail.get("found_hash") or "")[:16]
    return (f"(seq {record.get('seq')}): {detail.get('problem')}; last good seq "
            f"{detail.get('last_good_seq')} hash {good} (known by {detail.get('known_by')}), "
            f"found seq {detail.get('found_seq')} hash {found}")


def _count_lines(data: bytes) -> int:
    return data.count(b"\n") + (1 if data and not data.endswith(b"\n") else 0)


def _check(raw: bytes, seq: int, last: str, after_dropped: bool
           ) -> tuple[str | None, dict[str, Any]]:
    """What is wrong with one line after a record (seq, last), or None, and the record. The
    oldest kept record after rotation dropped older files links to a record no longer here."""
    try:
        record = json.loads(raw)
    except ValueError as exc:
        return f"not JSON ({exc})", {}
    if not isinstance(record, dict) or not isinstance(record.get("hash"), str) \
            or not isinstance(record.get("seq"), int) or not isinstance(record.get("prev"), str):
        return "not an audit record (seq, prev and hash)", {}
    if canonical(record).encode() != raw:
        return "not in canonical form: the line was edited", record
    body = {k: v for k, v in record.items() if k != "hash"}
    if hashlib.sha256(canonical(body).encode()).hexdigest() != record["hash"]:
        return "its hash does not match its content: the record was edited", record
    if after_dropped:
        return None, record
    if record["seq"] != seq + 1:
        return f"seq {record['seq']} follows {seq}: records are missing or repeated", record
    if record["prev"] != last:
        return "prev is not the hash of the record before: the chain is broken", record
    return None, record
