"""The rule of softplc/security/auth.py as deployed: a service bound off loopback (0.0.0.0 here,
reached through 127.0.0.1) needs credentials on every path but /healthz and the page; the
owner's key is kept in a 0600 file and compared in constant time; bound to loopback a request
without credentials may read, not change anything, and foreign Host headers are refused
(DNS rebinding)."""

from __future__ import annotations

import stat
from pathlib import Path

from softplc.api.server import ApiServer
from softplc.security import auth
from tests.api.conftest import ServerThread
from tests.api.helpers import call
from tests.fuzz.live import LivePlc

ROOT = Path(__file__).resolve().parents[2]


def test_bound_to_all_interfaces_the_token_is_required(tmp_path: Path) -> None:
    state = tmp_path / "state"
    with LivePlc(ROOT, ROOT / "programs" / "transport.yaml") as plc:
        server = ApiServer(plc.channel, plc.reader, plc.board, host="0.0.0.0", port=0,
                           state_dir=state)
        assert server.token_required  # not asked for: the bind address decides
        with ServerThread(server) as api:
            path = state / auth.TOKEN_FILE
            assert stat.S_IMODE(path.stat().st_mode) == 0o600
            token = path.read_text().strip()
            assert call(api.url, "GET", "/healthz").status == 200
            assert call(api.url, "GET", "/api/v1/status").status == 401
            assert call(api.url, "GET", "/api/v1/status",
                        headers={"Authorization": f"Bearer {token[:-1]}"}).status == 401
            good = {"Authorization": f"Bearer {token}"}
            assert call(api.url, "GET", "/api/v1/status", headers=good).status == 200
            assert call(api.url, "GET", "/api/v1/status",
                        headers={**good, "Host": "plc.example:8080"}).status == 200


def test_bound_to_loopback_reads_without_a_token_but_only_loopback_host_names(
        tmp_path: Path) -> None:
    with LivePlc(ROOT, ROOT / "programs" / "transport.yaml") as plc:
        server = ApiServer(plc.channel, plc.reader, plc.board, host="127.0.0.1", port=0,
                           state_dir=tmp_path / "state")
        with ServerThread(server) as api:
            path = tmp_path / "state" / auth.TOKEN_FILE
            assert stat.S_IMODE(path.stat().st_mode) == 0o600  # the owner's key, always made
            assert call(api.url, "GET", "/api/v1/status").status == 200
            for method, route in (("POST", "/api/v1/stop"), ("POST", "/api/v1/start"),
                                  ("PUT", "/api/v1/symbols/hold"), ("DELETE", "/api/v1/forces"),
                                  ("POST", "/api/v1/program"), ("GET", "/api/v1/audit")):
                refused = call(api.url, method, route, b'{"value": 1}')
                assert refused.status == 401, (method, route)
                assert refused.headers["WWW-Authenticate"].startswith("Bearer")
            assert plc.document()["state"] == "RUNNING"
            rebound = call(api.url, "GET", "/api/v1/status", headers={"Host": "evil.example"})
            assert rebound.status == 403


def test_the_comparison_is_constant_time() -> None:
    """hmac.compare_digest, not ==: checked by behaviour on equal-length near misses and
    by the implementation's use of it (timing itself is never asserted: noisy machine)."""
    import inspect

    token = "t" * 43
    assert auth.bearer_matches(f"Bearer {token}", token)
    assert not auth.bearer_matches(f"Bearer {'t' * 42}u", token)
    assert "hmac.compare_digest" in inspect.getsource(auth.bearer_matches)
