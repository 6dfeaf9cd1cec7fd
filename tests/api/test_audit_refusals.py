"""Refused requests in the audit trail (softplc/security/refusals.py): the rule on virtual time (no
socket, no sleep), then a real service on 127.0.0.1 port 0 flooded with 2,000 refused
requests: a bounded number of records, exact counts, older records kept, the chain intact,
accepted commands written before they are answered."""

from __future__ import annotations

import http.client
import math
import time
from pathlib import Path
from typing import Any

from softplc.api.access import Gate
from softplc.security.audit import AuditTrail
from softplc.security.refusals import WINDOW_S, Refusals
from softplc.security.roles import Role
from tests.api.conftest import Plc, ScanThread, make_server
from tests.api.helpers import ANSWER_WITHIN_S, TRANSPORT, call, owner_headers
from tests.support import eventually

WALL_S = 1_700_000_000.0
FLOOD = 2000


def failed(peer: str = "10.0.0.9", user: str | None = "nobody",
           route: str = "GET /api/v1/status") -> dict[str, Any]:
    return {"user": user, "role": None, "via": "failed", "peer": peer, "iface": "http",
            "action": "login", "outcome": "failed", "status": 401,
            "detail": {"route": route, "reason": "a wrong API key"}}


def test_the_first_refusal_at_once_its_repeats_one_record_per_window() -> None:
    rule = Refusals(window_s=10.0)
    first = rule.note(failed(), "GET /api/v1/status", 0.0)
    assert first == {**failed(), "detail": {**failed()["detail"], "refusals": 1}}
    routes = ["GET /api/v1/status", "GET /api/v1/events", "POST /api/v1/stop"]
    records = []
    for n in range(1, 250):  # 25 s at 10 a second, the route varied
        now_s = n / 10
        route = routes[n % 3]
        assert rule.note(failed(route=route), route, now_s) is None  # the key: not the route
        records += rule.due(now_s, WALL_S + now_s)
    records += rule.drain(25.0, WALL_S + 25.0)
    assert [r["detail"]["refusals"] for r in records] == [100, 100, 49]  # 0.1-10, 10.1-20, ..
    assert sum(sum(r["detail"]["routes"].values()) for r in records) == 249
    assert records[0]["detail"]["routes"] == {routes[1]: 34, routes[2]: 33, routes[0]: 33}
    assert records[0]["detail"]["first"].startswith("2023-11-14T22:13:20.1")
    assert records[0]["detail"]["last"].startswith("2023-11-14T22:13:30.0")
    assert all(r["user"] == "nobody" and r["outcome"] == "failed" for r in records)
    assert rule.open == 0


def test_peers_users_and_reasons_are_kept_apart_and_the_table_is_bounded() -> None:
    rule = Refusals(window_s=10.0, max_keys=4, max_keys_per_peer=2)
    at_once = [rule.note(failed(user=f"u{n}"), "GET /", 0.0) for n in range(50)]
    assert sum(r is not None for r in at_once) == 2  # that peer's share of the table
    at_once = [rule.note(failed(peer=f"10.0.1.{n}"), "GET /", 0.0) for n in range(20)]
    assert sum(r is not None for r in at_once) == 2  # the rest of the table
    denied = {**failed(), "action": "POST stop", "outcome": "denied", "detail": {"needs": "x"}}
    assert rule.note(denied, "POST /api/v1/stop", 0.0) is None  # no room: counted beyond
    (beyond_failed, beyond_denied) = rule.due(10.0, WALL_S)[-2:]
    assert beyond_failed["detail"]["refusals"] == 48 + 18
    assert beyond_failed["detail"]["peers"][:2] == ["10.0.0.9", "10.0.1.2"]
    assert beyond_failed["detail"]["more_peers"] == 19 - 8  # 19 peers beyond, 8 named
    assert beyond_denied["outcome"] == "denied" and beyond_denied["detail"]["refusals"] == 1


class Flood:
    """Refused requests over one keep-alive connection (another one if it is closed)."""

    def __init__(self, url: str) -> None:
        self.port = int(url.rsplit(":", 1)[1])
        self.conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
        self.answers: dict[int, int] = {}

    def send(self, method: str, path: str, headers: dict[str, str],
             body: bytes | None = None) -> None:
        for attempt in (1, 2):
            try:
                self.conn.request(method, path, body=body, headers=headers)
                answer = self.conn.getresponse()
                answer.read()
            except (http.client.HTTPException, ConnectionError):
                self.conn.close()
                self.conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
                if attempt == 2:
                    raise
                continue
            self.answers[answer.status] = self.answers.get(answer.status, 0) + 1
            return


def refusal_records(state: Path) -> list[dict[str, Any]]:
    return [r for r in AuditTrail(state).records()
            if r.get("outcome") in ("failed", "denied") and r.get("user") != "owner"]


def test_a_flood_of_refused_requests_is_a_few_records_with_exact_counts(
        plc_parts: Plc, scan: ScanThread, tmp_path: Path) -> None:
    state = tmp_path / "state"
    # A small trail (2 files of 16 KiB, ~70 records): 2,000 records would rotate out the
    # accepted commands written before the flood.
    small = AuditTrail(state, max_bytes=16 << 10, keep=1)
    handle = make_server(plc_parts, state)
    handle.server.gate = Gate(state, "", Role.VIEWER, audit=small)
    with handle as api:
        owner = owner_headers(api.url)
        for _ in range(3):  # accepted by the gate (refused by the PLC, which is EMPTY)
            assert call(api.url, "POST", "/api/v1/stop", headers=owner).status == 409
        flood = Flood(api.url)
        t0 = time.monotonic()
        for n in range(FLOOD):
            if n % 2:
                flood.send("POST", "/api/v1/stop", {})  # no credentials: 401, denied
            else:
                flood.send("GET", "/api/v1/status", {"Authorization": "Bearer nobody.wrong"})
        elapsed_s = time.monotonic() - t0
        flood.conn.close()
        assert flood.answers == {401: FLOOD}
        # An accepted command is neither delayed nor merged: in the trail once answered.
        assert call(api.url, "POST", "/api/v1/stop", headers=owner).status == 409
        newest = small.records()[-1]
        assert (newest["user"], newest["action"], newest["outcome"]) == (
            "owner", "POST stop", "refused")
    records = refusal_records(state)
    # Per kind: the first at once, one record per window the flood spanned, the rest at stop.
    assert len(records) <= 2 * (2 + math.ceil(elapsed_s / WINDOW_S)), len(records)
    counts = {"failed": 0, "denied": 0}
    for record in records:
        counts[record["outcome"]] += record["detail"]["refusals"]
    assert counts == {"failed": FLOOD // 2, "denied": FLOOD // 2}
    summary = next(r for r in records if r["detail"]["refusals"] > 1)
    assert summary["detail"]["first"] <= summary["detail"]["last"]
    owners = [r for r in small.records() if r.get("user") == "owner"]
    assert len(owners) == 4  # the three before the flood were not rotated away
    verdict = small.verify()
    assert verdict.ok, verdict


def test_a_window_closes_while_the_service_runs(api: Any) -> None:
    api.server.gate.refusals.rule.window_s = 0.5
    for _ in range(10):
        assert call(api.url, "POST", "/api/v1/stop").status == 401
    state = api.server.state_dir

    def summed() -> list[dict[str, Any]] | None:
        records = refusal_records(state)
        return records if sum(r["detail"]["refusals"] for r in records) == 10 else None

    records = eventually(summed, 30, "the window's record written while serving",
                         show=lambda: refusal_records(state))
    assert records[0]["detail"]["refusals"] == 1 and len(records) >= 2
    assert all(r["detail"]["routes"] == {"POST /api/v1/stop": r["detail"]["refusals"]}
               for r in records[1:])
    assert AuditTrail(state).verify().ok


def test_a_flood_of_malformed_commands_is_a_few_records_and_a_plc_refusal_stays_itemized(
        plc_parts: Plc, scan: ScanThread, tmp_path: Path) -> None:
    # The JSON bombs from an operator's key: each was one record with an fsync.
    state = tmp_path / "state"
    bombs = 400
    with make_server(plc_parts, state) as api:
        owner = owner_headers(api.url)
        assert call(api.url, "POST", "/api/v1/program?name=transport.yaml",
                    TRANSPORT.read_text(), timeout_s=ANSWER_WITHIN_S, owner=True).status == 200
        eventually(lambda: call(api.url, "GET", "/api/v1/symbols").body["symbols"])
        flood = Flood(api.url)
        t0 = time.monotonic()
        for n in range(bombs):
            body = b"[" * 2_000 if n % 2 else b'{"value":' * 400
            flood.send("PUT", "/api/v1/symbols/hold",
                       {**owner, "Content-Type": "application/json"}, body)
        elapsed_s = time.monotonic() - t0
        flood.conn.close()
        assert flood.answers == {400: bombs}, flood.answers
        # A command is an operator's action, whatever its outcome: written before its answer.
        stopped = call(api.url, "POST", "/api/v1/stop", headers=owner).status
        newest = AuditTrail(state).records()[-1]
        assert (newest["user"], newest["action"], newest["status"]) == (
            "owner", "POST stop", stopped)
    malformed = [r for r in AuditTrail(state).records() if r.get("status") == 400]
    # Per kind (the two bombs' messages): the first at once, one per window, the rest at stop.
    assert len(malformed) <= 2 * (2 + math.ceil(elapsed_s / WINDOW_S)), len(malformed)
    assert sum(r["detail"]["refusals"] for r in malformed) == bombs
    assert all(r["user"] == "owner" and r["outcome"] == "refused" for r in malformed)
    assert AuditTrail(state).verify().ok
