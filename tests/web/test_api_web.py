"""The page's routes and forcing through the real HTTP API (loopback, port 0): the net's
structure, the decimated live stream, force/unforce from the client and the CLI, forcing
refused without the token off loopback while the page itself loads without one.
"""

from __future__ import annotations

import http.client
import json
import time
from pathlib import Path

import pytest

from softplc.api.client import ApiClient, ApiError
from softplc.api.web import LIVE_HZ
from softplc.cli import main
from tests.api.conftest import Plc, ScanThread, ServerThread, make_server
from tests.api.helpers import ROOT, TRANSPORT, call
from tests.support import eventually

DRILLING = ROOT / "programs" / "drilling.yaml"


def running(api: ServerThread, program: Path = TRANSPORT) -> ApiClient:
    client = ApiClient(api.url)
    client.download(program)  # on a loaded machine its answer can be "pending" (202)
    eventually(lambda: client.status()["program_hash"], 60, "the download is applied")
    client.start()
    eventually(lambda: client.status()["state"] == "RUNNING", 30)
    return client


@pytest.mark.parametrize(("program", "places", "transitions", "instances"),
                         [(TRANSPORT, 8, 7, {"c1", "c2"}), (DRILLING, 8, 7, set())])
def test_the_net_route_gives_the_structure_of_each_case_study(
        api: ServerThread, program: Path, places: int, transitions: int,
        instances: set[str]) -> None:
    assert call(api.url, "GET", "/api/v1/net").status == 404  # nothing loaded yet
    running(api, program)
    net = eventually(lambda: (a := call(api.url, "GET", "/api/v1/net")).status == 200 and a.body)
    assert (len(net["nodes"]["places"]), len(net["nodes"]["transitions"])) == (places,
                                                                                transitions)
    assert {n["instance"] for n in net["nodes"]["places"]} - {None} == instances
    names = {n["name"] for n in net["nodes"]["places"] + net["nodes"]["transitions"]}
    assert all(a[0] in names and a[1] in names for a in net["arcs"])
    assert all("description" in s for s in net["symbols"])


def read_frames(url: str, seconds: float) -> list[dict[str, object]]:
    conn = http.client.HTTPConnection("127.0.0.1", int(url.rsplit(":", 1)[1]), timeout=5)
    frames = []
    try:
        conn.request("GET", "/api/v1/live")
        response = conn.getresponse()
        assert response.status == 200
        assert response.getheader("Content-Type", "").startswith("text/event-stream")
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            line = response.readline()
            if line.startswith(b"data: "):
                frames.append(json.loads(line[6:]))
    finally:
        conn.close()
    return frames


def test_the_live_stream_is_decimated_and_carries_marking_values_and_forces(
        api: ServerThread) -> None:
    client = running(api)
    client.force("s1_i", 1)
    frames = read_frames(api.url, 1.0)
    # The test scan thread scans every ~2 ms (500 scans/s); frames stay at the page's rate.
    assert 3 <= len(frames) <= LIVE_HZ + 2
    last = frames[-1]
    assert last["state"] == "RUNNING" and last["program"] == "transport"
    assert last["forced"] == {"s1_i": 1} and last["values"]["s1_i"] == 1
    assert sum(last["marking"].values()) >= 3
    assert "fired_counts" in last["net_live"] and "exec_p99_us" in last["timing"]
    # Only new scans: a frame follows a scan of the snapshot or of the board (the board can
    # catch up with the snapshot, on a loaded machine, with no scan in between).
    seen = [(f["scan_count"], f["board_scan_count"]) for f in frames]
    assert len(set(seen)) == len(frames) and seen == sorted(seen)


def test_forcing_from_the_client_changes_what_the_program_does(api: ServerThread) -> None:
    client = running(api)
    assert client.forces() == {}
    # c1.idle -> c1.moving needs a part at s1_i: the plant has none, the force gives one.
    reply = client.force("s1_i", True)
    assert reply["state"] == "RUNNING" and "s1_i = 1" in reply["message"]
    eventually(lambda: client.status()["marking"].get("c1.idle", 0) == 0)
    assert client.forces() == {"s1_i": 1}
    assert client.status()["forced"] == {"s1_i": 1}
    client.force("m2", 1)
    eventually(lambda: client.read_symbol("m2") is True)
    client.unforce("m2")
    eventually(lambda: client.forces() == {"s1_i": 1})
    client.unforce()
    eventually(lambda: client.forces() == {})
    with pytest.raises(ApiError) as unknown:
        client.force("nope", 1)
    assert unknown.value.status == 422 and "no symbol 'nope'" in unknown.value.message
    with pytest.raises(ApiError) as word:
        client.force("s1_i", 2)
    assert word.value.status == 422
    with pytest.raises(ApiError) as not_forced:
        client.unforce("s1_i")
    assert not_forced.value.status == 422


def test_force_and_unforce_from_the_cli(api: ServerThread,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    client = running(api)
    assert main(["force", "s2_o", "true", "--api", api.url]) == 0
    assert "s2_o = 1" in capsys.readouterr().out
    eventually(lambda: client.forces() == {"s2_o": 1})
    assert main(["status", "--api", api.url]) == 0
    eventually(lambda: "FORCED" in (main(["status", "--api", api.url]), capsys.readouterr().out)[1])
    assert main(["unforce", "--api", api.url]) == 0
    assert "released s2_o" in capsys.readouterr().out
    assert main(["force", "s2_o", "maybe", "--api", api.url]) == 1
    assert main(["unforce", "nothing_forced", "--api", api.url]) == 1
    assert "refused (HTTP 422)" in capsys.readouterr().err


def test_off_loopback_the_page_loads_but_forcing_needs_the_token(
        plc_parts: Plc, scan: ScanThread, tmp_path: Path) -> None:
    state = tmp_path / "state"
    with make_server(plc_parts, state, token_required=True) as api:
        page = call(api.url, "GET", "/")
        assert page.status == 200 and b"softplc" in page.raw
        assert "default-src 'self'" in page.headers["Content-Security-Policy"]
        for method, path, body in (("PUT", "/api/v1/forces/s1_i", b'{"value": 1}'),
                                   ("DELETE", "/api/v1/forces", None),
                                   ("GET", "/api/v1/net", None), ("GET", "/api/v1/live", None)):
            assert call(api.url, method, path, body).status == 401, path
        token = (state / "api_token").read_text().strip()
        client = ApiClient(api.url, token)
        client.download(TRANSPORT)
        assert client.force("s1_i", 1)["state"] == "STOPPED"
        eventually(lambda: client.forces() == {"s1_i": 1})
        # Same Origin rule as every write: a foreign page cannot force.
        refused = call(api.url, "PUT", "/api/v1/forces/s1_i", b'{"value": 0}',
                       {"Origin": "http://evil.example", "Authorization": f"Bearer {token}"})
        assert refused.status == 403


def test_a_foreign_host_header_gets_no_page(api: ServerThread) -> None:
    assert call(api.url, "GET", "/", headers={"Host": "evil.example"}).status == 403
    assert call(api.url, "GET", "/static/app.js", headers={"Host": "evil.example"}).status == 403
