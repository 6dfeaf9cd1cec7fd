"""The page's session cookie over plain HTTP, against a real ApiServer in front of a real scan
loop (issue 31): its flags (HttpOnly, SameSite=Strict, Path=/, 8 hours, no Secure without
TLS: tests/security/test_tls_process.py has it with), what it may do with the browser's
Origin and what it may not from another origin, the end of a session at logout, and a cookie
that names no session counting as no credential (DNS rebinding)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from http.cookies import SimpleCookie
from pathlib import Path

import pytest

from softplc.api.access import COOKIE
from softplc.security.audit import AuditTrail
from softplc.security.remembered import SESSION_S
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
from tests.api.helpers import Answer, call

PASSWORD = "operator-pass-1"


@pytest.fixture
def served(plc_parts: Plc, scan: ScanThread, tmp_path: Path  # noqa: F811 - fixtures
           ) -> Iterator[tuple[ServerThread, Path]]:
    state = tmp_path / "state"
    UserStore(state).add("op", Role.OPERATOR, PASSWORD)
    with make_server(plc_parts, state) as api:
        yield api, state


def log_in(api: ServerThread) -> tuple[Answer, str]:
    answer = call(api.url, "POST", "/api/v1/login", json.dumps(
        {"user": "op", "password": PASSWORD}), {"Content-Type": "application/json",
                                                "Origin": api.url})
    assert answer.status == 200, answer.raw
    header = answer.headers["Set-Cookie"]
    return answer, header


def test_the_cookie_is_httponly_strict_whole_site_a_shift_and_not_secure_over_http(
        served: tuple[ServerThread, Path]) -> None:
    api, _ = served
    answer, header = log_in(api)
    assert answer.body == {"user": "op", "role": "operator"}
    cookie = SimpleCookie(header)[COOKIE]
    assert len(cookie.value) >= 40  # 256 random bits
    assert cookie["httponly"] is True and cookie["samesite"] == "Strict"
    assert cookie["path"] == "/" and cookie["max-age"] == str(int(SESSION_S))
    assert not cookie["secure"] and "secure" not in header.lower()
    assert "domain" not in header.lower()  # this host only


def test_the_page_acts_with_its_origin_and_nothing_acts_from_another(
        served: tuple[ServerThread, Path]) -> None:
    api, state = served
    session = {"Cookie": f"{COOKIE}={SimpleCookie(log_in(api)[1])[COOKIE].value}"}
    who = call(api.url, "GET", "/api/v1/whoami", headers=session)
    assert who.body == {"user": "op", "role": "operator", "via": "session"}
    # What the browser sends with the page's fetch: its own origin. The guard lets it
    # through (409: nothing is loaded, the stop reached the scan).
    page = call(api.url, "POST", "/api/v1/stop", headers={**session, "Origin": api.url})
    assert page.status == 409 and page.body["outcome"] == "refused"
    foreign = call(api.url, "POST", "/api/v1/stop",
                   headers={**session, "Origin": "http://evil.example"})
    assert foreign.status == 403 and foreign.body["error"] == "cross-origin requests are refused"
    stops = [(r["user"], r["via"], r["status"]) for r in AuditTrail(state).records()
             if r["action"] == "POST stop"]
    assert stops == [("op", "session", 409)]  # the foreign one never reached a handler


def test_logout_ends_the_session_and_clears_the_cookie(
        served: tuple[ServerThread, Path]) -> None:
    api, _ = served
    session = {"Cookie": f"{COOKIE}={SimpleCookie(log_in(api)[1])[COOKIE].value}"}
    out = call(api.url, "POST", "/api/v1/logout", headers={**session, "Origin": api.url})
    assert out.status == 200
    cleared = SimpleCookie(out.headers["Set-Cookie"])[COOKIE]
    assert cleared.value == "" and cleared["max-age"] == "0"
    # The old cookie, replayed: no one (a viewer on loopback, as without credentials).
    who = call(api.url, "GET", "/api/v1/whoami", headers=session)
    assert who.body == {"user": None, "role": "viewer", "via": "anonymous"}
    assert call(api.url, "POST", "/api/v1/stop", headers={**session, "Origin": api.url}
                ).status == 401


def test_a_cookie_naming_no_session_is_no_credential_for_the_host_check(
        served: tuple[ServerThread, Path]) -> None:
    api, _ = served
    # A page on another site, rebound to 127.0.0.1, sends its own cookie of that name: it
    # must be refused as a request without credentials to a foreign Host is.
    rebound = {"Host": f"evil.example:{api.server.bound_port}"}
    assert call(api.url, "GET", "/api/v1/status", headers=rebound).status == 403
    forged = call(api.url, "GET", "/api/v1/status",
                  headers={**rebound, "Cookie": f"{COOKIE}=made-up"})
    assert forged.status == 403 and "loopback host only" in forged.body["error"]
    # A live session's cookie is a credential: the Host may then be any name of the PLC.
    session = {"Cookie": f"{COOKIE}={SimpleCookie(log_in(api)[1])[COOKIE].value}"}
    named = {"Host": f"plc.example:{api.server.bound_port}"}
    assert call(api.url, "GET", "/api/v1/status", headers={**named, **session}).status == 200
