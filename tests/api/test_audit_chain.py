"""The audit chain checked from where the last check ended (softplc/security/auditchain.py,
chainwatch.py): only appended records parsed, any byte of the verified part changed in place
found, a rotated or replaced file verified again in full; and a real service whose status
answers while a full verification is held, then checks only what was appended."""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path
from typing import Any

import pytest

from softplc.security.audit import GENESIS, MAX_BYTES, AuditTrail, canonical, utc_now
from tests.api.conftest import Plc, ScanThread, make_server
from tests.api.helpers import ANSWER_WITHIN_S, call
from tests.support import eventually


def entry(n: int) -> dict[str, Any]:
    return {"user": "op", "role": "operator", "via": "key", "peer": "127.0.0.1",
            "iface": "http", "action": "PUT symbols/hold", "outcome": "applied", "status": 200,
            "detail": {"value": n}}


def fill(state: Path, records: int) -> None:
    """A trail of `records` records in audit.jsonl, written at once (no lock, no fsync)."""
    state.mkdir(parents=True, exist_ok=True)
    lines, prev = [], GENESIS
    for seq in range(1, records + 1):
        record = {**entry(seq), "seq": seq, "time": utc_now(), "prev": prev}
        record["hash"] = prev = hashlib.sha256(canonical(record).encode()).hexdigest()
        lines.append(canonical(record) + "\n")
    (state / "audit.jsonl").write_text("".join(lines))


def change_in_place(path: Path, at: int, byte: int) -> None:
    """One byte written over, the file's inode and size kept."""
    with path.open("r+b") as handle:
        handle.seek(at)
        handle.write(bytes([byte]))


def test_appended_records_alone_are_parsed(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    fill(tmp_path, 50)
    full = trail.verify()
    assert full.ok and full.parsed == 50 and full.resume is not None
    written = [trail.append(entry(n)) for n in range(3)]
    tail = trail.verify_tail(full.resume)
    assert tail is not None and tail.ok and tail.parsed == 3
    assert (tail.records, tail.last_seq, tail.last_hash) == (53, 53, written[-1]["hash"])
    assert tail == trail.verify()  # the same verdict as a full verification
    again = trail.verify_tail(tail.resume) if tail.resume else None
    assert again is not None and again.ok and again.parsed == 0


def test_every_byte_of_the_verified_part_changed_in_place_is_found(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    for n in range(3):
        trail.append(entry(n))
    verified = trail.verify()
    assert verified.resume is not None
    trail.append(entry(3))  # the tail: appended after the verification
    original = trail.path.read_bytes()
    inode = trail.path.stat().st_ino
    for at in range(verified.resume.files[-1].size):
        change_in_place(trail.path, at, original[at] ^ 0x01)
        assert trail.verify_tail(verified.resume) is None, f"byte {at} changed: not noticed"
        assert not trail.verify().ok
        change_in_place(trail.path, at, original[at])
    assert trail.path.stat().st_ino == inode
    assert trail.path.read_bytes() == original
    tail = trail.verify_tail(verified.resume)
    assert tail is not None and tail.ok and tail.records == 4


def test_a_broken_tail_is_named_and_the_next_check_starts_from_before_it(
        tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    fill(tmp_path, 5)
    verified = trail.verify()
    assert verified.resume is not None
    with trail.path.open("ab") as handle:
        handle.write(b'{"seq": 6}\n')
    broken = trail.verify_tail(verified.resume)
    assert broken is not None and not broken.ok and broken.where == "audit.jsonl:6"
    assert broken.resume is None and broken == trail.verify()


def test_rotated_replaced_or_cut_files_need_a_full_verification(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path, max_bytes=600, keep=2)
    for n in range(5):
        trail.append(entry(n))
    verified = trail.verify()
    assert verified.resume is not None and len(verified.resume.files) >= 2
    rotated, newest = trail.files()[0], trail.path.read_bytes()
    change_in_place(rotated, 40, rotated.read_bytes()[40] ^ 0x01)  # an older file
    assert trail.verify_tail(verified.resume) is None
    change_in_place(rotated, 40, rotated.read_bytes()[40] ^ 0x01)
    assert trail.verify_tail(verified.resume) is not None
    with trail.path.open("r+b") as handle:  # cut
        handle.truncate(len(newest) - 1)
    assert trail.verify_tail(verified.resume) is None
    trail.path.write_bytes(newest)  # the same file again, as it was
    assert trail.verify_tail(verified.resume) is not None
    copy = tmp_path / "copy"
    copy.write_bytes(newest)
    os.replace(copy, trail.path)  # the same bytes in another file
    assert trail.verify_tail(verified.resume) is None
    verified = trail.verify()
    assert verified.resume is not None
    for n in range(3):
        trail.append(entry(n))  # the newest file rotates
    assert trail.verify_tail(verified.resume) is None
    assert trail.verify().ok


def test_an_anchor_is_found_in_the_tail_or_the_tail_was_cut(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path)
    fill(tmp_path, 5)
    verified = trail.verify()
    assert verified.resume is not None
    written = trail.append(entry(6))
    anchor = (written["seq"], written["hash"])
    found = trail.verify_tail(verified.resume, anchor)
    assert found is not None and found.ok and found.resume is not None
    later = trail.verify_tail(found.resume, anchor)  # the anchor now in the verified part
    assert later is not None and later.ok
    gone = trail.verify_tail(found.resume, (7, written["hash"]))
    assert gone is not None and not gone.ok and "cut" in str(gone.problem)
    assert trail.verify_tail(found.resume, (6, "f" * 64)) is None  # let a full check say


@pytest.fixture
def held(monkeypatch: pytest.MonkeyPatch) -> Any:
    """AuditTrail.verify (the full verification) held until released; its calls counted."""
    class Held:
        calls = 0
        entered = threading.Event()
        release = threading.Event()

    real = AuditTrail.verify

    def verify(self: AuditTrail, anchor: tuple[int, str] | None = None) -> Any:
        Held.calls += 1
        Held.entered.set()
        Held.release.wait(ANSWER_WITHIN_S + 30)  # longer than a status may take
        return real(self, anchor)

    monkeypatch.setattr(AuditTrail, "verify", verify)
    yield Held
    Held.release.set()


def test_status_never_waits_for_a_full_verification_and_then_parses_only_the_tail(
        plc_parts: Plc, scan: ScanThread, tmp_path: Path, held: Any) -> None:
    state, records = tmp_path / "state", 2000
    fill(state, records)
    assert (state / "audit.jsonl").stat().st_size < MAX_BYTES * 3 // 4  # no rotation below
    with make_server(plc_parts, state) as api:
        # The first check starts with the service, in a thread: once it is under way (and
        # held), status answers (a quiet run once asked before the thread had begun).
        assert held.entered.wait(ANSWER_WITHIN_S), "no verification started with the service"
        first = call(api.url, "GET", "/api/v1/status", timeout_s=ANSWER_WITHIN_S)
        assert first.status == 200
        assert held.calls == 1 and not held.release.is_set()  # answered while one was held
        assert first.body["audit"]["ok"] is None and first.body["audit"]["checked_at"] is None
        held.release.set()

        def audit(ok: bool | None = None) -> dict[str, Any] | None:
            found = dict(call(api.url, "GET", "/api/v1/status").body["audit"])
            return found if ok is None or found["ok"] is ok else None

        verdict = eventually(lambda: audit(True), 30, "the first verdict")
        assert verdict["records"] == records and verdict["checked_at"].endswith("Z")
        watch = api.server.gate.watch
        watch.interval_s = 0.0
        trail = AuditTrail(state)
        for n in range(5):
            trail.append(entry(n))
        eventually(lambda: (audit(True) or {}).get("records") == records + 5, 30,
                   "the appended records")
        assert held.calls == 1 and watch.full_checks == 1
        assert records + 5 <= watch.parsed <= records + 10  # not the whole trail again
        at = trail.path.read_bytes().index(b'"value":10}')  # in record 10: verified before
        change_in_place(trail.path, at + 8, ord("7"))
        broken = eventually(lambda: audit(False), 30, "the change found")
        assert broken["where"] == "audit.jsonl:10" and "edited" in broken["problem"]
        assert held.calls == 2 and watch.full_checks == 2
