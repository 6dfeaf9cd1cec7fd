"""The audit chain's head file is written as the state directory's other writers write: aside,
fsynced, renamed over the old one, and the directory fsynced (a head that a power loss could
leave empty, or naming a record the disk never got, reads as a break at the next start).

The real writer, on a real directory; os.fsync and os.replace are watched (and still do their
work) to see what reached the disk in which order.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest

from softplc.security.audit import AuditTrail
from softplc.security.auditbreak import HEAD_FILE, read_head


def _watch(monkeypatch: pytest.MonkeyPatch) -> list[tuple[str, str, str]]:
    events: list[tuple[str, str, str]] = []
    fsync: Callable[[int], None] = os.fsync
    replace = os.replace

    def watched_fsync(fd: int) -> None:
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"), ""))
        fsync(fd)

    def watched_replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        events.append(("replace", os.path.realpath(src), os.path.realpath(dst)))
        replace(src, dst)

    monkeypatch.setattr(os, "fsync", watched_fsync)
    monkeypatch.setattr(os, "replace", watched_replace)
    return events


def test_the_head_is_fsynced_renamed_and_its_directory_fsynced(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    trail = AuditTrail(tmp_path)
    trail.append({"action": "first", "outcome": "applied"})
    events = _watch(monkeypatch)
    record = trail.append({"action": "second", "outcome": "applied"})
    head = str((tmp_path / HEAD_FILE).resolve())
    directory = str(tmp_path.resolve())
    renames = [i for i, e in enumerate(events) if e[0] == "replace" and e[2] == head]
    assert len(renames) == 1, events
    at = renames[0]
    written = events[at][1]
    assert ("fsync", written, "") in events[:at], f"the head was renamed unsynced: {events}"
    assert ("fsync", directory, "") in events[at + 1:], \
        f"the directory was not synced after the head's rename: {events}"
    assert read_head(tmp_path / HEAD_FILE) == (record["seq"], record["hash"])
    assert sorted(p.name for p in tmp_path.iterdir() if HEAD_FILE in p.name) == [HEAD_FILE]
    assert (tmp_path / HEAD_FILE).stat().st_mode & 0o777 == 0o600
