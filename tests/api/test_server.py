"""Every endpoint of the service against a live scan loop, over a real socket."""

from __future__ import annotations

import json
from typing import Any

from aiohttp import web

from softplc.api.openapi import openapi_document
from softplc.api.server import MAX_BODY_BYTES
from tests.api.conftest import ServerThread
from tests.api.helpers import BAD_PROGRAM, DRILLING, TRANSPORT, Answer, call
from tests.support import eventually


def post(api: ServerThread, path: str, body: bytes | str | None = None,
         **headers: str) -> Answer:
    return call(api.url, "POST", f"/api/v1{path}", body, headers, owner=True)


def get(api: ServerThread, path: str) -> Answer:
    return call(api.url, "GET", f"/api/v1{path}")


def download(api: ServerThread, query: str = "?name=transport.yaml") -> Answer:
    return post(api, f"/program{query}", TRANSPORT.read_text())


def test_healthz_and_status_of_an_empty_plc(api: ServerThread) -> None:
    assert call(api.url, "GET", "/healthz").body == {"status": "ok"}
    status = eventually(lambda: (s := get(api, "/status").body).get("state") and s)
    assert status["state"] == "EMPTY"
    assert status["program"] is None
    assert {"scan_count", "marking", "timing", "start_mode", "last_event_seq"} <= status.keys()
    assert "symbols" not in status and "events" not in status


def test_download_start_and_status(api: ServerThread) -> None:
    answer = download(api)
    assert answer.status == 200, answer.raw
    assert answer.body["ok"] is True and answer.body["state"] == "STOPPED"
    started = post(api, "/start")
    assert started.status == 200 and started.body["state"] == "RUNNING"

    status = eventually(lambda: (s := get(api, "/status").body)["state"] == "RUNNING" and s)
    assert status["program"] == "transport"
    assert len(status["program_hash"]) == 64
    assert status["start_mode"] == "cold"
    assert {"p99_lateness_us", "overruns"} <= status["timing"].keys()
    assert eventually(lambda: sum(get(api, "/status").body["marking"].values()) > 0)


def test_bad_program_lists_every_problem_and_changes_nothing(api: ServerThread) -> None:
    assert download(api).status == 200
    answer = post(api, "/program?name=broken.yaml", BAD_PROGRAM)
    assert answer.status == 422
    body = answer.body
    assert body["error"].startswith("download refused")
    problems = body["problems"]
    assert len(problems) >= 4, problems  # two bad markings, an unknown place, a bad guard
    assert all(p.split(":")[0].endswith("broken.yaml") for p in problems)
    for line, what in ((4, "places.a.tokens"), (5, "places.b.tokens"),
                       (7, "transitions.t.from"), (7, "transitions.t.when")):
        assert any(f":{line}: {what}:" in p for p in problems), (line, what, problems)
    assert get(api, "/status").body["program"] == "transport"


def test_empty_or_undecodable_program_is_refused(api: ServerThread) -> None:
    empty = post(api, "/program", "  \n")
    assert empty.status == 422 and empty.body["problems"]
    assert post(api, "/program", b"\xff\xfe program").status == 400
    assert post(api, "/program?online=maybe", "x: 1\n").status == 400
    assert post(api, "/program?name=../../etc/passwd", "x: 1\n").status == 400


def test_refused_lifecycle_commands_are_409_with_state_and_command(api: ServerThread) -> None:
    answer = post(api, "/start")
    assert answer.status == 409
    assert "start" in answer.body["error"] and "EMPTY" in answer.body["error"]
    assert answer.body["state"] == "EMPTY"
    assert download(api).status == 200
    assert post(api, "/stop").status == 409


def test_the_lifecycle_walk_over_http(api: ServerThread) -> None:
    steps = [("/start", 409), ("/program", 200), ("/start", 200), ("/resume", 409),
             ("/stop", 200), ("/resume", 200), ("/kill", 200), ("/start", 409),
             ("/reset", 200), ("/start", 200)]
    for path, expected in steps:
        answer = download(api) if path == "/program" else post(api, path)
        assert answer.status == expected, (path, answer.raw)


def test_download_while_running_needs_online_change(api: ServerThread) -> None:
    assert download(api).status == 200
    assert post(api, "/start").status == 200
    refused = download(api)
    assert refused.status == 409 and "online" in refused.body["error"]
    online = download(api, "?name=transport.yaml&online=true")
    assert online.status == 200 and online.body["state"] == "RUNNING"
    by_header = post(api, "/program?name=transport.yaml", TRANSPORT.read_text(),
                     **{"X-Softplc-Online": "true"})
    assert by_header.status == 200


def test_drilling_replaces_transport_online(api: ServerThread) -> None:
    assert download(api).status == 200 and post(api, "/start").status == 200
    answer = post(api, "/program?name=drilling.yaml&online=true", DRILLING.read_text())
    assert answer.status == 200, answer.raw
    eventually(lambda: get(api, "/status").body["program"] == "drilling")


def _symbols(api: ServerThread) -> dict[str, Any]:
    answer = get(api, "/symbols")
    assert answer.status == 200
    symbols: dict[str, Any] = answer.body["symbols"]
    return symbols


def test_symbols_read(api: ServerThread) -> None:
    assert _symbols(api) == {}
    assert download(api).status == 200
    symbols = eventually(lambda: _symbols(api))
    assert symbols["m1"] == {"name": "m1", "address": "%QX0.0", "type": "bool",
                             "direction": "out", "value": False, "raw": 0}
    assert symbols["parts_delivered"]["value"] == 0
    one = get(api, "/symbols/hold")
    assert one.status == 200 and one.body["address"] == "%MX0.0"
    missing = get(api, "/symbols/nope")
    assert missing.status == 404 and "nope" in missing.body["error"]


def put(api: ServerThread, name: str, body: Any) -> Answer:
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    return call(api.url, "PUT", f"/api/v1/symbols/{name}", raw,
                {"Content-Type": "application/json"}, owner=True)


def test_symbol_write_is_journaled_and_seen_by_the_scan(api: ServerThread) -> None:
    assert download(api).status == 200
    eventually(lambda: _symbols(api))
    answer = put(api, "hold", {"value": True})
    assert answer.status == 202
    assert answer.body == {"name": "hold", "address": "%MX0.0", "value": True, "queued": True}
    eventually(lambda: get(api, "/symbols/hold").body["value"] is True)
    assert post(api, "/start").status == 200  # outputs stay safe while STOPPED
    assert put(api, "parts_delivered", {"value": 1234}).status == 202
    eventually(lambda: get(api, "/symbols/parts_delivered").body["value"] == 1234)


def test_symbol_write_validation(api: ServerThread) -> None:
    assert download(api).status == 200
    eventually(lambda: _symbols(api))
    assert put(api, "nope", {"value": 1}).status == 404
    assert put(api, "s1_i", {"value": 1}).status == 403
    for body in ({"value": 2}, {"value": "on"}, {"value": None}, {}, [1]):
        answer = put(api, "hold", body)
        assert answer.status == 422, body
        assert answer.body["error"]
    for body in ({"value": 70000}, {"value": -1}, {"value": True}, {"value": 1.5}):
        assert put(api, "parts_delivered", body).status == 422, body
    assert put(api, "hold", b"{not json").status == 400


def test_body_too_large_is_413(api: ServerThread) -> None:
    big = b"#" * (MAX_BODY_BYTES + 1)
    answer = post(api, "/program", big)
    assert answer.status == 413 and "error" in answer.body
    assert put(api, "hold", big).status == 413


def test_unknown_paths_and_methods_are_json_4xx(api: ServerThread) -> None:
    missing = call(api.url, "GET", "/api/v1/nothing")
    assert missing.status == 404 and missing.body["problems"] == []
    wrong = call(api.url, "DELETE", "/api/v1/start")
    assert wrong.status == 405 and "error" in wrong.body


def test_foreign_host_and_cross_origin_requests_are_refused(api: ServerThread) -> None:
    rebound = call(api.url, "GET", "/api/v1/status", headers={"Host": "evil.example:8080"})
    assert rebound.status == 403
    port = api.server.bound_port
    csrf = call(api.url, "POST", "/api/v1/start",
                headers={"Origin": "http://evil.example", "Host": f"127.0.0.1:{port}"})
    assert csrf.status == 403
    same = call(api.url, "GET", "/api/v1/status",
                headers={"Origin": f"http://127.0.0.1:{port}", "Host": f"127.0.0.1:{port}"})
    assert same.status == 200
    other_scheme = call(api.url, "POST", "/api/v1/start", headers={
        "Origin": f"https://127.0.0.1:{port}", "Host": f"127.0.0.1:{port}"})
    assert other_scheme.status == 403  # the scheme is part of the origin (issue 38)


def test_openapi_describes_every_route(api: ServerThread) -> None:
    answer = get(api, "/openapi.json")
    assert answer.status == 200
    document = answer.body
    assert document["openapi"].startswith("3.")
    assert document == openapi_document()
    app = api.server.build_app()
    served = {(r.method.lower(), r.resource.canonical) for r in app.router.routes()
              if r.resource is not None and r.method != "HEAD"}
    described = {(method, path) for path, item in document["paths"].items()
                 for method in item}
    assert served == described
    for item in document["paths"].values():
        for operation in item.values():
            assert operation["responses"]


def test_build_app_is_an_aiohttp_application(api: ServerThread) -> None:
    assert isinstance(api.server.build_app(), web.Application)
