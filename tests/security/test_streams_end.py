"""An open event stream is decided again before everything it sends (issue 38, item 3): a
removed user's or a changed password's stream ends with `event: end` at its next event or
heartbeat, as HTTP requests and OPC UA calls are refused at their next request."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.security.users import UserStore
from tests.api.conftest import (  # noqa: F401 - plc_parts and scan are pytest fixtures
    ScanThread,
    ServerThread,
    plc_parts,
    scan,
)
from tests.security.test_audit_stream import (  # noqa: F401 - served is a pytest fixture
    OP_PASSWORD,
    Sse,
    basic_op,
    served,
)


@pytest.mark.parametrize("change", ["remove", "passwd", "revoke key"])
def test_an_event_stream_ends_when_its_user_loses_the_right(
        served: tuple[ServerThread, Path], change: str) -> None:  # noqa: F811
    api, state = served
    users = UserStore(state)
    headers = basic_op()
    if change == "revoke key":
        headers = {"Authorization": f"Bearer {users.new_key('op')}"}
    stream = Sse(api.url, "/api/v1/events", headers)
    try:
        assert stream.response.status == 200
        if change == "remove":
            users.remove("op")
            reason = "the user was removed"
        elif change == "passwd":
            users.set_password("op", OP_PASSWORD + "-new")
            reason = "the password was changed"
        else:
            users.revoke_key("op")
            reason = "the API key was replaced or revoked"
        said = stream.said_within(10.0)  # bounded: heartbeats every 0.3 s keep it going
        assert said[:1] == ["event: end"] and reason in said[1], said
        with pytest.raises(EOFError):
            stream.block()
    finally:
        stream.close()
