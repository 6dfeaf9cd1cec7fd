"""The audit trail as events (`GET /api/v1/audit/events`, admin; issue 31) from a real
ApiServer in front of a real scan loop: only an admin opens it, records from this server and
from another process (`softplc users`) arrive once each in seq order, `Last-Event-ID`
replays what the trail keeps, a viewer's event stream carries none of it, a stream whose key
is revoked ends; and the follower under it keeps its place across rotation (no socket)."""

from __future__ import annotations

import base64
import contextlib
import http.client
import json
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.security.audit import AuditTrail, Follower
from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.api.conftest import (  # noqa: F401 - plc_parts and scan are pytest fixtures
    Plc,
    ScanThread,
    ServerThread,
    make_server,
    plc_parts,
    scan,
)
from tests.api.helpers import call

ROOT = Path(__file__).resolve().parents[2]
OP_PASSWORD = "operator-pass-1"


class Sse:
    """A raw server-sent events reader of one GET."""

    def __init__(self, url: str, path: str, headers: dict[str, str]) -> None:
        host, _, port = url.removeprefix("http://").partition(":")
        self.conn = http.client.HTTPConnection(host, int(port), timeout=20)
        self.conn.request("GET", path, headers=headers)
        self.response = self.conn.getresponse()
        self.pending = b""

    def block(self) -> list[str]:
        """The next block of lines that is not a comment (heartbeats, `: connected`)."""
        while True:
            while b"\n\n" not in self.pending:
                chunk = self.response.read1(65536)
                if not chunk:
                    raise EOFError("the stream ended")
                self.pending += chunk
            raw, _, self.pending = self.pending.partition(b"\n\n")
            lines = [line for line in raw.decode().split("\n")
                     if line and not line.startswith(":") and not line.startswith("retry:")]
            if lines:
                return lines

    def records(self, count: int) -> list[tuple[int, dict[str, Any]]]:
        found = []
        while len(found) < count:
            lines = self.block()
            assert lines[0].startswith("id: "), lines
            found.append((int(lines[0][4:]), json.loads(lines[1].removeprefix("data: "))))
        return found

    def said_within(self, seconds: float) -> list[str]:
        """Every line but comments (heartbeats) received within `seconds`."""
        assert self.conn.sock is not None
        deadline = time.monotonic() + seconds
        lines: list[str] = []
        with contextlib.suppress(TimeoutError, OSError, EOFError):
            while (left := deadline - time.monotonic()) > 0:
                self.conn.sock.settimeout(left)
                chunk = self.response.read1(65536)
                if not chunk:
                    break
                lines += [line for line in chunk.decode().split("\n")
                          if line and not line.startswith((":", "retry:"))]
        return lines

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
def served(plc_parts: Plc, scan: ScanThread, tmp_path: Path  # noqa: F811 - fixtures
           ) -> Iterator[tuple[ServerThread, Path]]:
    state = tmp_path / "state"
    users = UserStore(state)
    users.add("op", Role.OPERATOR, OP_PASSWORD)
    with make_server(plc_parts, state, heartbeat_s=0.3) as api:
        yield api, state


def owner(state: Path) -> dict[str, str]:
    return {"Authorization": "Bearer " + (state / "api_token").read_text().strip()}


def basic_op() -> dict[str, str]:
    return {"Authorization": "Basic " + base64.b64encode(f"op:{OP_PASSWORD}".encode()).decode()}


def test_only_an_admin_opens_the_audit_stream(served: tuple[ServerThread, Path]) -> None:
    api, state = served
    assert call(api.url, "GET", "/api/v1/audit/events").status == 401  # loopback: a viewer
    refused = call(api.url, "GET", "/api/v1/audit/events", headers=basic_op())
    assert refused.status == 403 and "needs admin; op is operator" in refused.body["error"]
    stream = Sse(api.url, "/api/v1/audit/events", owner(state))
    try:
        assert stream.response.status == 200
        assert stream.response.getheader("Content-Type", "").startswith("text/event-stream")
    finally:
        stream.close()


def test_records_of_every_writer_arrive_once_in_order_and_replay(
        served: tuple[ServerThread, Path]) -> None:
    api, state = served
    before = AuditTrail(state).records()  # the 403 and 401s of other requests, if any
    stream = Sse(api.url, "/api/v1/audit/events", owner(state))
    viewer = Sse(api.url, "/api/v1/events", {})  # the program's events, as a viewer reads them
    try:
        assert stream.response.status == 200 and viewer.response.status == 200
        assert call(api.url, "POST", "/api/v1/stop", headers=basic_op()).status == 409  # EMPTY
        added = subprocess.run([sys.executable, "-m", "softplc.cli", "users", "add", "view",
                                "--role", "viewer", "--state-dir", str(state)], cwd=ROOT,
                               input="viewer-pass-1\n", capture_output=True, text=True,
                               timeout=120)
        assert added.returncode == 0, added.stderr
        (first_id, stop), (second_id, user) = stream.records(2)
        assert (stop["user"], stop["action"], stop["outcome"], stop["iface"]) == (
            "op", "POST stop", "refused", "http")
        assert (user["action"], user["iface"]) == ("users add view", "cli")
        assert (first_id, second_id) == (stop["seq"], user["seq"]) and second_id == first_id + 1
        trail = AuditTrail(state).records()
        assert trail[len(before):] == [stop, user]  # exactly the trail's lines, hash included
        assert viewer.said_within(1.0) == []  # no program, no events; no audit record either
    finally:
        stream.close()
        viewer.close()
    again = Sse(api.url, "/api/v1/audit/events", {**owner(state), "Last-Event-ID": str(first_id)})
    try:
        assert again.records(1) == [(second_id, user)]
    finally:
        again.close()


def test_the_stream_ends_once_its_key_no_longer_gives_admin(
        served: tuple[ServerThread, Path]) -> None:
    api, state = served
    users = UserStore(state)
    users.add("boss", Role.ADMIN, "admin-pass-123")
    key = users.new_key("boss")
    stream = Sse(api.url, "/api/v1/audit/events", {"Authorization": f"Bearer {key}"})
    try:
        assert stream.response.status == 200
        users.set_role("boss", Role.ENGINEER)
        assert stream.block() == ["event: end",
                                  'data: {"reason": "audit needs admin; boss has engineer"}']
        with pytest.raises(EOFError):
            stream.block()
    finally:
        stream.close()


def entry(n: int) -> dict[str, object]:
    return {"user": "op", "role": "operator", "peer": "127.0.0.1", "iface": "http",
            "action": f"POST stop {n}", "outcome": "applied", "status": 200,
            "detail": {"message": "x" * 100}}


def test_the_follower_keeps_its_place_across_rotation(tmp_path: Path) -> None:
    trail = AuditTrail(tmp_path, max_bytes=2000, keep=3)
    trail.append(entry(0))
    follower = Follower(trail)  # from now: record 1 is history
    seen: list[int] = []
    for n in range(1, 40):
        trail.append(entry(n))
        if n % 3 == 0:  # several records, sometimes a rotation, between two polls
            records, skipped = follower.poll(100)
            assert skipped == 0
            seen += [r["seq"] for r in records]
    records, skipped = follower.poll(100)
    seen += [r["seq"] for r in records]
    assert seen == list(range(2, 41)) and skipped == 0
    assert len(trail.files()) == 4  # it did rotate, and dropped the oldest files
    assert follower.poll(100) == ([], 0)
    late = Follower(trail, after=1)  # its next records went with the dropped files
    records, skipped = late.poll(5)
    assert [r["seq"] for r in records] == list(range(36, 41))
    assert skipped == records[0]["seq"] - 2 and trail.verify().ok
