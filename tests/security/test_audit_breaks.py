"""Evidence is never lost silently (issue 38, item 5): a trail cut or rewritten behind a
writer gets a break record (the last good seq and hash, what was found) before the next
record, whether the writer is the one that wrote last (its own memory) or was started after
the cut (the head file, softplc/security/auditbreak.py); `softplc audit --verify` names every
break and exits 1 afterwards. A trail that was not cut gets none: several writers at once,
a writer idle while others rotated its last record away, a trail from before head files.
And a real `softplc run` whose trail is cut under it: its next record comes after a break
record, verify exits 1, status names the break."""

from __future__ import annotations

import base64
import hashlib
import json
import multiprocessing
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from softplc.cli import main
from softplc.security.audit import AuditTrail, canonical
from softplc.security.auditbreak import BREAK_ACTION
from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.api.helpers import call
from tests.support import eventually, free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]


def entry(n: int, iface: str = "http") -> dict[str, Any]:
    return {"user": "op", "role": "operator", "via": "key", "peer": "127.0.0.1",
            "iface": iface, "action": f"POST stop {n}", "outcome": "applied", "status": 200,
            "detail": {"value": n}}


def lines(trail: AuditTrail) -> list[bytes]:
    return trail.path.read_bytes().splitlines(keepends=True)


def cut(trail: AuditTrail, keep: int) -> dict[str, Any]:
    """The trail cut back to its first `keep` records; the first record removed."""
    kept = lines(trail)
    trail.path.write_bytes(b"".join(kept[:keep]))
    return dict(json.loads(kept[keep]))


def verify_cli(state: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """`softplc audit --verify`, offline, as an auditor runs it: exit code, what it printed."""
    code = main(["audit", "--verify", "--state-dir", str(state)])
    printed = capsys.readouterr()
    return code, printed.out + printed.err


def breaks(trail: AuditTrail) -> list[dict[str, Any]]:
    return [r for r in trail.records() if r.get("action") == BREAK_ACTION]


def test_a_trail_cut_under_a_live_writer_gets_a_break_record_first(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trail = AuditTrail(tmp_path)
    written = [trail.append(entry(n)) for n in range(6)]
    cut(trail, 3)
    trail.head.unlink()  # the head gone too: what this writer wrote last still shows the cut
    asked = trail.append(entry(6, iface="opcua"))
    found = trail.records()
    assert [r["seq"] for r in found] == [1, 2, 3, 4, 5]
    mark = found[3]
    assert mark["action"] == BREAK_ACTION and mark["break"] is True
    assert mark["iface"] == "opcua" and mark["prev"] == written[2]["hash"]  # onto what is there
    assert mark["detail"]["last_good_seq"] == 6
    assert mark["detail"]["last_good_hash"] == written[5]["hash"]
    assert mark["detail"]["known_by"] == "this writer"
    assert (mark["detail"]["found_seq"], mark["detail"]["found_hash"]) == (
        3, written[2]["hash"])
    assert "cut" in mark["detail"]["problem"]
    assert found[4] == asked and asked["prev"] == mark["hash"] and asked["detail"] == {"value": 6}
    verdict = AuditTrail(tmp_path).verify()
    assert not verdict.ok and verdict.where == "audit.jsonl:4"
    assert [where for where, _ in verdict.breaks] == ["audit.jsonl:4"]
    assert "last good seq 6" in verdict.breaks[0][1]
    code, err = verify_cli(tmp_path, capsys)
    assert code == 1 and "break at audit.jsonl:4 (seq 4)" in err and "seq 6" in err
    trail.append(entry(7))  # the writer goes on: one break, not one per record
    assert len(breaks(trail)) == 1 and not AuditTrail(tmp_path).verify().ok


def test_a_trail_cut_before_a_restart_gets_a_break_record_from_the_head(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    before = AuditTrail(tmp_path)
    written = [before.append(entry(n)) for n in range(5)]
    cut(before, 2)
    code, err = verify_cli(tmp_path, capsys)  # found offline before anything is appended
    assert code == 1 and "record 5" in err and "cut" in err
    restarted = AuditTrail(tmp_path)  # the service started again: it remembers nothing
    restarted.append(entry(5))
    (mark,) = breaks(restarted)
    assert mark["seq"] == 3 and mark["detail"]["known_by"] == "audit.head"
    assert (mark["detail"]["last_good_seq"], mark["detail"]["last_good_hash"]) == (
        5, written[4]["hash"])
    code, err = verify_cli(tmp_path, capsys)
    assert code == 1 and "break at audit.jsonl:3 (seq 3)" in err


def test_a_rewritten_trail_gets_a_break_record(tmp_path: Path) -> None:
    """The last records replaced by others that chain (hashes computed again): the seq goes
    on, the hash the head names is not there."""
    trail = AuditTrail(tmp_path)
    written = [trail.append(entry(n)) for n in range(4)]
    forged, prev = [], written[1]["hash"]
    for record in written[2:]:
        record = {**{k: v for k, v in record.items() if k != "hash"}, "prev": prev,
                  "detail": {"value": "forged"}}
        record["hash"] = prev = hashlib.sha256(canonical(record).encode()).hexdigest()
        forged.append(canonical(record).encode() + b"\n")
    trail.path.write_bytes(b"".join(lines(trail)[:2] + forged))
    assert AuditTrail(tmp_path).verify().ok is False  # the head names the real seq 4
    AuditTrail(tmp_path).append(entry(4))
    (mark,) = breaks(trail)
    assert mark["seq"] == 5 and "rewritten" in mark["detail"]["problem"]
    assert mark["detail"]["last_good_hash"] == written[3]["hash"]
    assert mark["detail"]["found_hash"] == prev


def test_a_truncated_newest_file_or_a_removed_trail_gets_a_break_record(
        tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path, max_bytes=600, keep=2)
    for n in range(8):
        trail.append(entry(n))
    assert len(trail.files()) >= 2
    trail.path.write_bytes(b"")  # truncated: the last record is in audit.1.jsonl
    AuditTrail(tmp_path, max_bytes=600, keep=2).append(entry(8))
    assert [m["detail"]["last_good_seq"] for m in breaks(trail)] == [8]
    for path in trail.files():
        path.unlink()  # the whole trail removed; the head stays
    again = AuditTrail(tmp_path, max_bytes=600, keep=2)
    again.append(entry(9))
    (mark,) = breaks(again)
    assert mark["seq"] == 1 and mark["detail"]["found_seq"] == 0
    assert mark["detail"]["last_good_seq"] == 8  # the record after the first break (seq 7)
    assert not again.verify().ok and again.verify().where == "audit.jsonl:1"


def test_a_garbled_head_is_named_and_gets_a_break_record(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    trail = AuditTrail(tmp_path)
    for n in range(3):
        trail.append(entry(n))
    trail.head.write_bytes(b"\x00\x17garbage")
    code, err = verify_cli(tmp_path, capsys)
    assert code == 1 and "audit.head" in err and "unreadable" in err
    AuditTrail(tmp_path).append(entry(3))
    (mark,) = breaks(trail)
    assert "audit.head unreadable" in mark["detail"]["problem"]
    assert mark["detail"]["last_good_seq"] is None and mark["detail"]["found_seq"] == 3


def test_no_break_without_a_cut(tmp_path: Path) -> None:
    """An idle writer whose last record rotated away, a trail written before head files, an
    entry that claims to be a break: none of them is one."""
    idle = AuditTrail(tmp_path, max_bytes=600, keep=2)
    idle.append(entry(0))
    busy = AuditTrail(tmp_path, max_bytes=600, keep=2)
    for n in range(30):
        busy.append(entry(n))
    assert busy.verify().first_seq > 1  # seq 1, the idle writer's, dropped
    idle.append(entry(1))
    idle.head.unlink()  # as a trail written before heads were
    AuditTrail(tmp_path, max_bytes=600, keep=2).append({**entry(2), "break": True})
    assert breaks(idle) == [] and idle.verify().ok
    assert all("break" not in r for r in idle.records())


def _append_many(state: str, who: int) -> None:
    trail = AuditTrail(state, max_bytes=4000)
    for n in range(40):
        trail.append({**entry(n), "user": f"p{who}"})


def test_several_writers_at_once_leave_no_break(tmp_path: Path) -> None:
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_append_many, args=(str(tmp_path), w)) for w in range(4)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(60)
        assert worker.exitcode == 0
    trail = AuditTrail(tmp_path, max_bytes=4000)
    verdict = trail.verify()
    assert verdict.ok and verdict.last_seq == 160 and verdict.breaks == ()
    assert len(trail.files()) > 1  # rotated while they wrote


# -- a real service ----------------------------------------------------------------------


def test_a_trail_cut_under_a_running_service_is_recorded_and_verify_shows_it(
        tmp_path: Path) -> None:
    UserStore(tmp_path / "state").add("op", Role.OPERATOR, "operator-password")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    op = {"Authorization": "Basic " + base64.b64encode(b"op:operator-password").decode()}
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--start", "--api",
                      f"127.0.0.1:{port}", "--modbus", "off", "--opcua", "off", "--state-dir",
                      "state", "--quiet", "--period", "10ms"],
                     lambda: call(url, "GET", "/api/v1/status", timeout_s=5).status == 200,
                     cwd=tmp_path, stdout=subprocess.DEVNULL, what="softplc run answering"):
        for route in ("stop", "resume", "stop"):
            assert call(url, "POST", f"/api/v1/{route}", headers=op).status == 200
        trail = AuditTrail(tmp_path / "state")
        gone = cut(trail, len(lines(trail)) - 2)  # the last two records: resume and stop
        assert call(url, "POST", "/api/v1/resume", headers=op).status == 200
        verified = subprocess.run([sys.executable, "-m", "softplc.cli", "audit", "--verify",
                                   "--state-dir", "state"], cwd=tmp_path, capture_output=True,
                                  text=True, timeout=120, check=False)
        assert verified.returncode == 1 and "break at audit.jsonl:" in verified.stderr
        (mark,) = breaks(trail)
        assert mark["iface"] == "http" and mark["detail"]["last_good_seq"] == gone["seq"] + 1
        assert trail.records()[-1]["action"] == "POST resume"
        audit = eventually(lambda: (s := call(url, "GET", "/api/v1/status").body["audit"])
                           ["ok"] is False and s, 30, "status naming the break")
        assert audit["breaks"] and audit["where"] == audit["breaks"][0]["where"]
