"""Random requests never get a 5xx or a traceback, and every error body is the JSON shape.

Bounded: a few dozen examples against one live service (hypothesis, not schemathesis, to
keep the dev dependencies as they are)."""

from __future__ import annotations

import json
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.api.conftest import Plc, ScanThread, make_server
from tests.api.helpers import ANSWER_WITHIN_S, TRANSPORT, call

PATHS = ["/healthz", "/api/v1/status", "/api/v1/program", "/api/v1/start", "/api/v1/stop",
         "/api/v1/resume", "/api/v1/reset", "/api/v1/kill", "/api/v1/symbols",
         "/api/v1/symbols/hold", "/api/v1/symbols/s1_i", "/api/v1/symbols/parts_delivered",
         "/api/v1/openapi.json", "/api/v1/nothing", "/api/v1/symbols/%00", "/"]

ROUTES = [("GET", "/api/v1/status"), ("POST", "/api/v1/program"),
          ("POST", "/api/v1/program?online=true&name=x.yaml"), ("POST", "/api/v1/start"),
          ("POST", "/api/v1/stop"), ("POST", "/api/v1/resume"), ("POST", "/api/v1/reset"),
          ("POST", "/api/v1/kill"), ("GET", "/api/v1/symbols"), ("GET", "/api/v1/symbols/hold"),
          ("PUT", "/api/v1/symbols/hold"), ("PUT", "/api/v1/symbols/parts_delivered"),
          ("PUT", "/api/v1/symbols/s1_i"), ("PUT", "/api/v1/symbols/nope")]
paths = st.one_of(
    st.sampled_from(PATHS),
    st.builds(lambda base, tail: base + tail, st.sampled_from(PATHS),
              st.text("abc/?=&%.-_01", max_size=12)),
)
requests = st.one_of(
    st.sampled_from(ROUTES),  # mostly real routes with random bodies and headers
    st.sampled_from(ROUTES),
    st.tuples(st.sampled_from(["GET", "POST", "PUT", "DELETE", "PATCH"]), paths),
)
bodies = st.one_of(
    st.none(),
    st.binary(max_size=256),
    st.builds(lambda v: json.dumps({"value": v}).encode(),
              st.one_of(st.integers(-70000, 70000), st.booleans(), st.none(), st.text(max_size=5),
                        st.floats(allow_nan=False))),
    st.just(TRANSPORT.read_bytes()),
    st.builds(lambda text: text.encode(), st.text(max_size=200)),
)
headers = st.fixed_dictionaries({}, optional={
    "Content-Type": st.sampled_from(["application/json", "application/yaml", "text/plain",
                                     "multipart/form-data", "x/y"]),
    "X-Softplc-Online": st.sampled_from(["true", "false", "1", "maybe", ""]),
    "Last-Event-ID": st.sampled_from(["1", "x", ""]),
})


def test_random_requests_never_5xx(plc_parts: Plc, scan: ScanThread, tmp_path: Path) -> None:
    with make_server(plc_parts, tmp_path) as api:

        @settings(max_examples=40, deadline=None, database=None,
                  suppress_health_check=[HealthCheck.too_slow])
        @given(request=requests, body=bodies, extra=headers)
        def check(request: tuple[str, str], body: bytes | None, extra: dict[str, str]) -> None:
            method, path = request
            if path.endswith("/events") or "/events?" in path:
                return  # an endless stream; covered in test_events
            # What is checked is the server's answer, whatever the load, never the client
            # giving up first.
            answer = call(api.url, method, path, body, extra, timeout_s=ANSWER_WITHIN_S)
            assert answer.status < 500, (method, path, answer.raw[:300])
            if answer.status >= 400 and method != "HEAD":
                document = answer.body
                assert isinstance(document["error"], str)
                assert isinstance(document["problems"], list)
                assert "Traceback" not in answer.raw.decode("utf-8", "replace")

        check()
