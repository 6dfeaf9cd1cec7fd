"""The API token never appears in logs, stdout or stderr, whatever a client sends: the
right token, a near miss of it, the token in places it does not belong (query string
aside: a URL is logged by design, docs/security.md)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from softplc.api.server import ApiServer
from softplc.security import auth
from tests.api.conftest import ServerThread
from tests.api.helpers import call
from tests.fuzz.live import LivePlc

ROOT = Path(__file__).resolve().parents[2]


def test_the_token_never_reaches_logs_or_output(tmp_path: Path, caplog: pytest.LogCaptureFixture,
                                                 capfd: pytest.CaptureFixture[str]) -> None:
    caplog.set_level(logging.DEBUG)
    state = tmp_path / "state"
    with LivePlc(ROOT, ROOT / "programs" / "transport.yaml") as plc:
        server = ApiServer(plc.channel, plc.reader, plc.board, host="127.0.0.1", port=0,
                           state_dir=state, token_required=True)
        with ServerThread(server) as api:
            token = (state / auth.TOKEN_FILE).read_text().strip()
            near_misses = [token[:-1] + ("A" if token[-1] != "A" else "B"), token + "x",
                           token[1:], token.upper()]
            statuses = []
            for given in [token, *near_misses]:
                for header in (f"Bearer {given}", f"Basic {given}", given):
                    headers = {"Authorization": header}
                    for method, path, body in (("GET", "/api/v1/status", None),
                                               ("POST", "/api/v1/start", None),
                                               ("PUT", "/api/v1/symbols/hold", '{"value": 1}'),
                                               ("POST", "/api/v1/program", "places: ["),
                                               ("GET", "/api/v1/nothing", None)):
                        statuses.append(call(api.url, method, path, body, headers).status)
            # the token where a careless client might put it: other headers, cookies
            for name in ("X-Api-Token", "Cookie", "Origin", "Referer", "User-Agent"):
                statuses.append(call(api.url, "GET", "/api/v1/status",
                                     headers={name: token}).status)
    out, err = capfd.readouterr()
    assert 200 in statuses and 401 in statuses  # good and bad tokens were both exercised
    assert "/api/v1/status" in caplog.text  # the access log was captured: it can leak
    everything = caplog.text + out + err
    for secret in [token, *near_misses]:
        assert secret not in everything
    assert token[:20] not in everything  # not even a prefix of it
