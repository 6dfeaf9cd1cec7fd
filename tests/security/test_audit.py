"""The audit trail's files (softplc/security/audit.py): a hash chain that any changed byte
breaks, appends from several processes at once, rotation that keeps the chain."""

from __future__ import annotations

import json
import multiprocessing
import stat
from pathlib import Path

from softplc.security.audit import GENESIS, AuditTrail, parse_since


def entry(n: int) -> dict[str, object]:
    return {"user": "op", "role": "operator", "peer": "127.0.0.1", "iface": "http",
            "action": f"POST stop {n}", "outcome": "applied", "status": 200,
            "detail": {"value": n}}


def test_records_chain_and_verify(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    written = [trail.append(entry(n)) for n in range(3)]
    assert [r["seq"] for r in written] == [1, 2, 3]
    assert written[0]["prev"] == GENESIS
    assert written[1]["prev"] == written[0]["hash"] and written[2]["prev"] == written[1]["hash"]
    assert written[0]["time"].endswith("Z")
    assert stat.S_IMODE(trail.path.stat().st_mode) == 0o600
    verdict = trail.verify()
    assert verdict.ok and verdict.records == 3 and verdict.last_hash == written[2]["hash"]
    assert trail.records() == written
    assert trail.records(limit=1) == written[-1:]
    assert trail.records(since="9999") == []


def test_every_single_byte_change_is_found(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    for n in range(3):
        trail.append(entry(n))
    original = trail.path.read_bytes()
    for at in range(len(original)):
        for changed in {original[at] ^ 0x01, ord("x") if original[at] != ord("x") else ord("y")}:
            trail.path.write_bytes(original[:at] + bytes([changed]) + original[at + 1:])
            verdict = trail.verify()
            assert not verdict.ok, f"byte {at} changed to {chr(changed)!r} not noticed"
            assert verdict.where is not None and verdict.where.startswith("audit.jsonl:")
    trail.path.write_bytes(original)
    assert trail.verify().ok


def test_removed_or_reordered_records_are_found(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    for n in range(4):
        trail.append(entry(n))
    lines = trail.path.read_bytes().splitlines(keepends=True)
    for broken in (lines[1:], lines[:1] + lines[2:], [lines[1], lines[0], *lines[2:]]):
        trail.path.write_bytes(b"".join(broken))
        assert not trail.verify().ok
    trail.path.write_bytes(b"".join(lines[:3]))  # the tail cut: the head file names it
    verdict = trail.verify()
    assert not verdict.ok and "record 4" in str(verdict.problem) and "cut" in str(verdict.problem)
    trail.head.unlink()  # as a trail written before heads were: only an anchor shows it
    assert trail.verify().ok
    last = json.loads(lines[3])
    verdict = trail.verify(anchor=(last["seq"], last["hash"]))
    assert not verdict.ok and "gone" in str(verdict.problem)


def test_rotation_is_bounded_and_keeps_the_chain(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path, max_bytes=600, keep=2)
    for n in range(40):
        trail.append(entry(n))
    files = trail.files()
    assert [p.name for p in files] == ["audit.2.jsonl", "audit.1.jsonl", "audit.jsonl"]
    assert all(p.stat().st_size < 600 + 400 for p in files)
    first_of_current = json.loads(trail.path.read_bytes().splitlines()[0])
    last_of_previous = json.loads(files[1].read_bytes().splitlines()[-1])
    assert first_of_current["prev"] == last_of_previous["hash"]
    assert first_of_current["seq"] == last_of_previous["seq"] + 1
    verdict = trail.verify()
    assert verdict.ok and verdict.last_seq == 40 and verdict.first_seq > 1  # oldest dropped
    (tmp_path / "audit.1.jsonl").unlink()  # a whole file taken out of the middle
    assert not trail.verify().ok


def _append_many(state: str, who: int) -> None:
    trail = AuditTrail(state)
    for n in range(25):
        trail.append({**entry(n), "user": f"p{who}"})


def test_several_processes_append_without_breaking_the_chain(tmp_path: Path) -> None:
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_append_many, args=(str(tmp_path), w)) for w in range(4)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(60)
        assert worker.exitcode == 0
    verdict = AuditTrail(tmp_path).verify()
    assert verdict.ok and verdict.records == 100 and verdict.last_seq == 100


def test_since_takes_iso_times_and_durations() -> None:
    assert parse_since("2025-03-01") == "2025-03-01T00:00:00.000Z"
    assert parse_since("2025-03-01T10:00+02:00") == "2025-03-01T08:00:00.000Z"
    assert parse_since("2h") < parse_since("1h")
