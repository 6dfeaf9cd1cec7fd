"""The owner's key (STATE_DIR/api_token): made at every start, stored 0600, reused, required
for everything off loopback, never shown; on loopback a request without credentials may
read (docs/security.md, users and roles)."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest

from softplc.api.server import ApiServer
from softplc.security import auth
from softplc.security.roles import Role
from tests.api.conftest import Plc, ScanThread, make_server
from tests.api.helpers import call


@pytest.mark.parametrize(("host", "loopback"), [
    ("127.0.0.1", True), ("127.5.6.7", True), ("::1", True), ("[::1]", True),
    ("localhost", True), ("LOCALHOST", True), ("0.0.0.0", False), ("::", False), ("", False),
    ("10.0.0.7", False), ("plc.example", False), ("192.168.1.2", False)])
def test_loopback_rule(host: str, loopback: bool) -> None:
    assert auth.is_loopback(host) is loopback
    assert auth.token_required(host, None) is (not loopback)
    assert auth.token_required(host, True) is True
    assert auth.token_required(host, False) is False


def test_a_server_bound_off_loopback_requires_a_token(plc_parts: Plc, tmp_path: Path) -> None:
    server = ApiServer(plc_parts.channel, plc_parts.reader, plc_parts.board, host="0.0.0.0",
                       port=0, state_dir=tmp_path)
    assert server.token_required and server.gate.anonymous is None
    assert server.token_file == tmp_path / "api_token"
    local = ApiServer(plc_parts.channel, plc_parts.reader, plc_parts.board, state_dir=tmp_path)
    assert not local.token_required and local.gate.anonymous is Role.VIEWER
    assert local.token_file == tmp_path / "api_token"  # the owner's key: made at every start
    assert (local.host, local.port) == ("127.0.0.1", 8080)


def test_token_file_is_created_0600_and_reused(tmp_path: Path) -> None:
    state = tmp_path / "state"
    token = auth.load_or_create_token(state)
    path = state / auth.TOKEN_FILE
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert len(token) >= 40
    assert auth.load_or_create_token(state) == token
    path.chmod(0o644)
    assert auth.load_or_create_token(state) == token
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert auth.load_or_create_token(tmp_path / "other") != token


def test_unusable_token_files_are_reported_without_their_content(tmp_path: Path) -> None:
    (tmp_path / auth.TOKEN_FILE).write_text("\n")
    with pytest.raises(auth.TokenFileError, match="empty"):
        auth.load_or_create_token(tmp_path)
    other = tmp_path / "d"
    (other / auth.TOKEN_FILE).mkdir(parents=True)
    with pytest.raises(auth.TokenFileError, match="not a regular file"):
        auth.load_or_create_token(other)


def test_bearer_header_check() -> None:
    assert auth.bearer_matches("Bearer abc", "abc")
    assert auth.bearer_matches("bearer abc", "abc")
    for header in (None, "", "Bearer", "Bearer abd", "Basic abc", "abc", "Bearer abcd"):
        assert not auth.bearer_matches(header, "abc")


def test_client_token_sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(auth.TOKEN_ENV, raising=False)
    monkeypatch.setenv(auth.INDEX_ENV, str(tmp_path / "index"))
    assert auth.client_token(None, None) is None
    assert auth.client_token(None, tmp_path) is None
    (tmp_path / auth.TOKEN_FILE).write_text("from-file\n")
    assert auth.client_token(None, tmp_path) == "from-file"
    monkeypatch.setenv(auth.TOKEN_ENV, "from-env")
    assert auth.client_token(None, tmp_path) == "from-env"
    assert auth.client_token("given", tmp_path) == "given"


def test_token_enforced_on_every_path_but_healthz(plc_parts: Plc, scan: ScanThread,
                                                   tmp_path: Path) -> None:
    state = tmp_path / "state"
    with make_server(plc_parts, state, token_required=True) as api:
        token = (state / auth.TOKEN_FILE).read_text().strip()
        assert stat.S_IMODE((state / auth.TOKEN_FILE).stat().st_mode) == 0o600
        answers = []
        for method, path in (("GET", "/api/v1/status"), ("POST", "/api/v1/start"),
                             ("GET", "/api/v1/symbols"), ("GET", "/api/v1/openapi.json"),
                             ("GET", "/api/v1/events"), ("PUT", "/api/v1/symbols/x"),
                             ("GET", "/api/v1/nothing")):
            for headers in ({}, {"Authorization": "Bearer wrong"},
                            {"Authorization": f"Basic {token}"},
                            {"Authorization": f"Bearer {token}x"}):
                answer = call(api.url, method, path, headers=headers)
                assert answer.status == 401, (method, path, headers)
                assert answer.headers["WWW-Authenticate"].startswith("Bearer")
                answers.append(answer)
        assert call(api.url, "GET", "/healthz").status == 200
        good = {"Authorization": f"Bearer {token}"}
        answers.append(call(api.url, "GET", "/api/v1/status", headers=good))
        answers.append(call(api.url, "GET", "/api/v1/openapi.json", headers=good))
        answers.append(call(api.url, "POST", "/api/v1/start", headers=good))
        assert [a.status for a in answers[-3:]] == [200, 200, 409]
        # A token-guarded service answers whatever Host it is reached by.
        other_host = call(api.url, "GET", "/api/v1/status", headers={**good, "Host": "plc.lan"})
        assert other_host.status == 200
        for answer in answers:
            assert token not in answer.raw.decode()
            assert all(token not in value for value in answer.headers.values())

    with make_server(plc_parts, state, token_required=True) as again:  # restart: same token
        status = call(again.url, "GET", "/api/v1/status", headers=good)
        assert status.status == 200
        assert (state / auth.TOKEN_FILE).read_text().strip() == token


def test_token_never_logged(plc_parts: Plc, scan: ScanThread, tmp_path: Path,
                            caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("DEBUG")
    state = tmp_path / "state"
    with make_server(plc_parts, state, token_required=True) as api:
        token = (state / auth.TOKEN_FILE).read_text().strip()
        call(api.url, "GET", "/api/v1/status", headers={"Authorization": f"Bearer {token}"})
        call(api.url, "GET", "/api/v1/status", headers={"Authorization": "Bearer nope"})
    assert token not in caplog.text
