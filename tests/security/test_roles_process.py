"""Users, roles and the audit trail against a real `softplc run` on a fresh state directory
(issue 31): users added with the CLI (passwords on stdin), a viewer's stop refused (403) and
audited, an operator's stop applied and audited with the user's name, loopback without
credentials reading but not stopping, the owner's `softplc stop` working as before, the
chain verified and found broken after one byte of the trail changed, wrong passwords
backing off and every one of them counted in the trail."""

from __future__ import annotations

import base64
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient
from softplc.security.refusals import WINDOW_S
from tests.api.helpers import Answer, call
from tests.support import eventually, free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
PASSWORDS = {"op": "operator-pass-1", "view": "viewer-pass-1"}


def softplc(*argv: str, cwd: Path, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *argv], cwd=cwd, input=stdin,
                          capture_output=True, text=True, timeout=120)


def basic(name: str, password: str | None = None) -> dict[str, str]:
    pair = f"{name}:{PASSWORDS[name] if password is None else password}".encode()
    return {"Authorization": "Basic " + base64.b64encode(pair).decode()}


@pytest.fixture(scope="module")
def plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path]]:
    """`softplc run transport.yaml --start` on a fresh state directory with two users."""
    where = tmp_path_factory.mktemp("plc")
    for name, role in (("op", "operator"), ("view", "viewer")):
        added = softplc("users", "add", name, "--role", role, "--state-dir", "state",
                        cwd=where, stdin=PASSWORDS[name] + "\n")
        assert added.returncode == 0, added.stderr
        assert PASSWORDS[name] not in added.stdout + added.stderr
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--start", "--api",
                      f"127.0.0.1:{port}", "--modbus", "off", "--opcua", "off", "--state-dir",
                      "state", "--quiet", "--period", "10ms"],
                     lambda: _state(url) == "RUNNING", cwd=where, stdout=subprocess.DEVNULL,
                     what="softplc run answering and RUNNING"):
        yield url, where


def _state(url: str) -> str:
    answer = call(url, "GET", "/api/v1/status", timeout_s=5)  # no credentials: a viewer
    return str(answer.body["state"]) if answer.status == 200 else ""


def audit_lines(where: Path) -> list[dict[str, Any]]:
    shown = softplc("audit", "--json", "--state-dir", "state", cwd=where)
    assert shown.returncode == 0, shown.stderr
    return [json.loads(line) for line in shown.stdout.splitlines()]


def test_roles_decide_and_the_trail_says_who(plc: tuple[str, Path]) -> None:
    url, where = plc
    assert call(url, "GET", "/api/v1/status").status == 200  # loopback, no credentials: read
    anonymous = call(url, "POST", "/api/v1/stop")
    assert anonymous.status == 401 and _state(url) == "RUNNING"
    viewer = call(url, "POST", "/api/v1/stop", headers=basic("view"))
    assert viewer.status == 403 and "view is viewer" in viewer.body["error"]
    assert _state(url) == "RUNNING"
    assert call(url, "GET", "/api/v1/whoami", headers=basic("view")).body["role"] == "viewer"
    stopped = call(url, "POST", "/api/v1/stop", headers=basic("op"))
    assert stopped.status == 200 and stopped.body["state"] == "STOPPED"
    forced = call(url, "PUT", "/api/v1/forces/hold", b'{"value": 1}', basic("op"))
    assert forced.status == 403  # forcing is an engineer's

    records = audit_lines(where)
    assert [(r["user"], r["action"]) for r in records[:2]] == [
        ("owner", "users add op"), ("owner", "users add view")]
    denied = [r for r in records if r["outcome"] == "denied"]
    assert {(r["user"], r["role"], r["action"]) for r in denied} >= {
        (None, "viewer", "POST stop"), ("view", "viewer", "POST stop"),
        ("op", "operator", "PUT forces/hold")}
    applied = [r for r in records if r["action"] == "POST stop" and r["outcome"] == "applied"]
    assert len(applied) == 1 and applied[0]["user"] == "op" and applied[0]["role"] == "operator"
    assert applied[0]["peer"] == "127.0.0.1" and applied[0]["iface"] == "http"
    assert str(applied[0]["time"]).endswith("Z")


def test_the_owners_cli_needs_nothing_and_an_admin_reads_the_trail(
        plc: tuple[str, Path]) -> None:
    url, where = plc
    assert softplc("resume", "--api", url, cwd=ROOT).returncode == 0  # no --state-dir given
    assert _state(url) == "RUNNING"
    done = softplc("stop", "--api", url, "--state-dir", "state", cwd=where)
    assert done.returncode == 0, done.stderr
    assert _state(url) == "STOPPED"
    assert call(url, "GET", "/api/v1/audit", headers=basic("op")).status == 403
    owner = ApiClient(url, state_dir=where / "state")
    trail = owner.audit(limit=5)
    assert trail["chain"]["ok"] and trail["records"][-1]["user"] == "owner"
    assert owner.status()["audit"]["ok"] is True


def test_one_changed_byte_breaks_the_chain(plc: tuple[str, Path]) -> None:
    url, where = plc
    verified = softplc("audit", "--verify", "--state-dir", "state", cwd=where)
    assert verified.returncode == 0 and "audit trail ok" in verified.stdout
    path = where / "state" / "audit.jsonl"
    original = path.read_bytes()
    at = len(original) // 2
    path.write_bytes(original[:at] + bytes([original[at] ^ 0x01]) + original[at + 1:])
    try:
        broken = softplc("audit", "--verify", "--state-dir", "state", cwd=where)
        assert broken.returncode == 1 and "BROKEN at audit.jsonl:" in broken.stderr
        client = ApiClient(url, state_dir=where / "state")
        eventually(lambda: client.status()["audit"]["ok"] is False, 20,
                   "status reporting the broken chain")
    finally:
        path.write_bytes(original)


def test_wrong_passwords_back_off_and_are_audited(plc: tuple[str, Path]) -> None:
    url, where = plc
    answers: list[Answer] = []
    deadline = time.monotonic() + 60
    while not answers or answers[-1].status != 429:
        assert time.monotonic() < deadline and len(answers) < 10, [a.status for a in answers]
        answers.append(call(url, "GET", "/api/v1/whoami", headers=basic("op", "not-it-at-all")))
    assert {a.status for a in answers[:-1]} == {401}
    assert int(answers[-1].headers["Retry-After"]) >= 1
    # The owner's key is no password: a peer backing off still reaches the PLC with it.
    assert softplc("status", "--api", url, cwd=ROOT).returncode == 0
    # Every failure and the 429 are in the trail: the first of each at once, the repeats
    # counted into one record when their window closes (docs/security.md, refused requests).
    sent = {"failed": len(answers) - 1, "refused": 1}

    def counted() -> list[dict[str, Any]] | None:
        records = [r for r in audit_lines(where) if r["action"] == "login"
                   and r["outcome"] in sent and r["user"] == "op"]
        total = {o: sum(r["detail"]["refusals"] for r in records if r["outcome"] == o)
                 for o in sent}
        return records if total == sent else None

    records = eventually(counted, WINDOW_S + 30, "every failed login counted in the trail",
                         step_s=0.5, show=lambda: audit_lines(where)[-3:])
    assert all(r["role"] is None for r in records)
    assert [r["detail"]["refusals"] for r in records[:2]] == [1, 1]
