"""Breaks of the audit trail: a record known to have been written, found gone or changed.

Owns: the head file (STATE_DIR/audit.head: seq and hash of the newest record, replaced by
every append under the trail's lock, so that a writer started later, the CLI or a restarted
service, knows what the trail held), the comparison of the trail's newest records with what
a writer knows (its own last record and the head), and the break record an append writes
before anything else when they differ (auditchain.py names it in every verification).
Does not know: how records are chained, written or rotated (audit.py, auditchain.py), HTTP.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

from softplc.core.errors import SoftplcError
from softplc.security.auditchain import Anchor, canonical
from softplc.security.files import write_private

HEAD_FILE: Final = "audit.head"
BREAK_ACTION: Final = "audit trail break"


class HeadUnreadable(SoftplcError, ValueError):
    """The head file is there but holds no head: why."""


def read_head(path: Path) -> Anchor | None:
    """The (seq, hash) `path` names; None when there is no head file (a trail written before
    heads were, or none yet)."""
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise HeadUnreadable(exc.strerror or type(exc).__name__) from None
    try:
        head = json.loads(raw)
        seq, digest = head["seq"], head["hash"]
    except (ValueError, TypeError, KeyError):
        raise HeadUnreadable("not a head record") from None
    if not isinstance(seq, int) or not isinstance(digest, str) or len(digest) != 64:
        raise HeadUnreadable("not a head record")
    return seq, digest


def write_head(path: Path, anchor: Anchor) -> None:
    """Replace the head file (the trail's lock held): written aside, fsynced, renamed over it
    and the directory fsynced (files.py), as the state directory's other writers do, so that
    after a power loss the head is the old one or the new one, whole, and the record it names
    was fsynced before it."""
    write_private(path, (canonical({"hash": anchor[1], "seq": anchor[0]}) + "\n").encode(),
                  sync_directory=True)


def mismatch(anchor: Anchor, last: Anchor, find: Callable[[int], str | None]) -> str | None:
    """What is wrong with the trail whose newest record is `last` for a writer that knows
    `anchor` was written, or None. `find` looks an older seq up: None when it is not there
    (a rotated file dropped it)."""
    seq, digest = anchor
    if seq > last[0]:
        return (f"the trail was cut: it ends at seq {last[0]}, record {seq} and any after it "
                "are gone")
    found = last[1] if seq == last[0] else find(seq)
    if found is not None and found != digest:
        return f"the trail was rewritten: record {seq} is not the one written"
    return None


def break_entry(problem: str, known_by: str, good: Anchor | None, found: Anchor,
                iface: Any) -> dict[str, Any]:
    """The record an append writes first when it finds the trail broken; `iface` is the
    writer's, so that the record says which door found it."""
    return {"user": None, "role": None, "via": None, "peer": None, "iface": iface,
            "action": BREAK_ACTION, "outcome": "failed", "status": None, "break": True,
            "detail": {"problem": problem, "known_by": known_by,
                       "last_good_seq": good[0] if good else None,
                       "last_good_hash": good[1] if good else None,
                       "found_seq": found[0], "found_hash": found[1]}}


def find_break(known: Anchor | None, head_path: Path, last: Anchor,
               find: Callable[[int], str | None], iface: Any) -> dict[str, Any] | None:
    """The break record to write before the next one, or None: the trail does not hold what
    this writer wrote last (`known`) or what the head file names, or the head is unreadable.
    The newest of the two is named as the last good record."""
    try:
        head = read_head(head_path)
    except HeadUnreadable as exc:
        return break_entry(f"{head_path.name} unreadable ({exc}): whether records are gone "
                           "is unknown", "this writer" if known else head_path.name, known,
                           last, iface)
    checks = [(a, who) for a, who in ((known, "this writer"), (head, head_path.name)) if a]
    for anchor, who in sorted(checks, key=lambda c: -c[0][0]):
        problem = mismatch(anchor, last, find)
        if problem is not None:
            return break_entry(problem, who, anchor, last, iface)
    return None


def hash_of(paths: Sequence[Path], seq: int) -> str | None:
    """The hash of record `seq` in `paths` (searched newest first, only lines that name the
    seq parsed), or None when no file holds it."""
    needle = f'"seq":{seq},'.encode()
    for path in reversed(paths):
        with contextlib.suppress(FileNotFoundError):
            data = path.read_bytes()
            at = data.find(needle)
            while at >= 0:
                start, end = data.rfind(b"\n", 0, at) + 1, data.find(b"\n", at)
                with contextlib.suppress(ValueError, TypeError, KeyError):
                    record = json.loads(data[start:end if end >= 0 else len(data)])
                    if record["seq"] == seq:
                        return str(record["hash"])
                at = data.find(needle, at + 1)
    return None
