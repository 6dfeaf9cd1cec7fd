"""Breakpoints against a real `softplc run` (issue 32 item 2's done-when): `make run`'s
transport PLC pauses when `handed_over` fires; status and the page's frame show the pause;
the scan count stands (no watchdog, no hang fault while it stands); `softplc step` advances
it by exactly one; `softplc continue` runs on; the outputs hold. Over HTTP as the owner."""

from __future__ import annotations

import contextlib
import io
import time
from collections.abc import Iterator

import pytest

from softplc.api.client import ApiClient
from softplc.api.web import live_frame
from softplc.cli import main
from tests.api.helpers import call
from tests.debug.live import status, transport_plc
from tests.support import eventually


def cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    with transport_plc(tmp_path_factory) as plc:
        yield plc


def test_break_on_handed_over_step_and_continue(server: tuple[str, str]) -> None:
    url, state = server
    owner = ("--api", url, "--state-dir", state)
    code, out, err = cli("break", "add", "transition", "handed_over", *owner)
    assert code == 0, err
    assert out.startswith("break: b1: handed_over fires (outputs hold while paused)")
    doc = eventually(lambda: (s := status(url)).get("paused") and s, 90, "the pause",
                     step_s=0.1)
    paused = doc["paused"]
    assert doc["state"] == "RUNNING" and paused["reason"] == "b1: handed_over fires"
    count = paused["scan_count"]
    assert eventually(lambda: status(url)["scan_count"] == count, 5, "the snapshot's count")
    values = ApiClient(url).symbols()
    time.sleep(1.5)  # paused longer than the watchdog's hard limit of one scan
    again = status(url)
    assert (again["scan_count"], again["fault_code"], again["state"]) == (count, 0, "RUNNING")
    outputs = {n: v["value"] for n, v in ApiClient(url).symbols().items()
               if v["direction"] == "out"}
    assert outputs == {n: v["value"] for n, v in values.items() if v["direction"] == "out"}
    frame = live_frame(again, None, None, [])  # what the page draws from the board
    assert frame["paused"]["reason"] == "b1: handed_over fires"
    code, out, err = cli("break", "list", *owner)
    assert code == 0 and "b1: handed_over fires" in out and f"scan count {count}" in out

    code, out, err = cli("step", *owner)
    assert code == 0, err
    assert eventually(lambda: (s := status(url)).get("paused")
                      and s["paused"]["scan_count"] == count + 1, 10, "one step")
    time.sleep(0.3)
    assert status(url)["scan_count"] == count + 1  # exactly one, then paused again

    code, out, err = cli("continue", *owner)
    assert code == 0, err
    assert eventually(lambda: status(url)["scan_count"] > count + 20, 10, "running on")
    assert cli("break", "clear", *owner)[0] == 0
    assert eventually(lambda: not status(url).get("breakpoints"), 5, "no breakpoints")
    # The API's answer names the breakpoint it made (what a client removes it by)
    added = ApiClient(url, state_dir=state).add_breakpoint("enabled", "hand_over")
    assert added["breakpoint"] == "b2" and added["message"].startswith("break: b2: ")
    assert ApiClient(url, state_dir=state).remove_breakpoint("b2")["ok"]
    assert cli("step", *owner)[0] == 1  # not paused: refused, naming what works


def test_breakpoint_routes_need_an_engineer(server: tuple[str, str]) -> None:
    url, _ = server
    # Without credentials on loopback: a viewer, who reads breakpoints and changes nothing.
    assert call(url, "GET", "/api/v1/breakpoints").status == 200
    body = '{"on": "fire", "transition": "handed_over"}'
    for method, path in (("POST", "/api/v1/breakpoints"), ("DELETE", "/api/v1/breakpoints"),
                         ("DELETE", "/api/v1/breakpoints/b1"), ("POST", "/api/v1/step"),
                         ("POST", "/api/v1/continue")):
        assert call(url, method, path, body if method == "POST" else None).status == 401
    assert call(url, "POST", "/api/v1/continue", owner=True).status == 409  # not paused
