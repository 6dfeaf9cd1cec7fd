"""One back-off for every door of a PLC (issue 38, item 5; softplc/security/backoff.py):
failures counted through one Backoff close the user name and the peer at another on the same
state directory (the HTTP and OPC UA processes), counts from several processes at once are
not lost, a corrupt table is one log line and an empty table, never a dead service; and
through the real doors: wrong passwords over HTTP refuse an OPC UA login of the same name,
with the right password, while it backs off."""

from __future__ import annotations

import asyncio
import base64
import http.client
import json
import logging
import multiprocessing
import stat
import subprocess
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from asyncua import ua

from softplc.security.backoff import (
    BACKOFF_ENTRIES,
    BACKOFF_FILE,
    BACKOFF_FORGET_S,
    FREE_FAILURES,
    Backoff,
)
from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.api.helpers import call
from tests.opcua.conftest import patient_client
from tests.support import free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
USER, PEER = ("user", "op"), ("peer", "10.0.0.9")


def test_failures_at_one_door_close_the_name_and_peer_at_another(tmp_path: Path) -> None:
    now = [1000.0]
    http_door = Backoff(lambda: now[0], state_dir=tmp_path)
    opcua_door = Backoff(lambda: now[0], state_dir=tmp_path)
    for _ in range(FREE_FAILURES + 1):
        http_door.failed(USER, PEER)
    assert opcua_door.wait_s(USER) == 1.0 and opcua_door.wait_s(PEER) == 1.0
    assert opcua_door.wait_s(("user", "other"), ("peer", "10.0.0.10")) == 0
    opcua_door.failed(USER)  # counted on from the HTTP door's four
    assert http_door.wait_s(USER) == 2.0
    assert stat.S_IMODE((tmp_path / BACKOFF_FILE).stat().st_mode) == 0o600
    opcua_door.succeeded(USER)
    assert http_door.wait_s(USER) == 0 and http_door.wait_s(PEER) == 1.0
    restarted = Backoff(lambda: now[0], state_dir=tmp_path)  # a service started again
    assert restarted.wait_s(PEER) == 1.0
    now[0] += 1.0 + BACKOFF_FORGET_S + 1  # long after its closure ended: forgotten
    restarted.failed(("user", "someone"))
    assert PEER not in restarted._table and http_door.wait_s(PEER) == 0


def test_the_table_is_bounded_and_a_wall_clock_step_waits_no_longer_than_the_cap(
        tmp_path: Path) -> None:
    now = [1000.0]
    door = Backoff(lambda: now[0], state_dir=tmp_path)
    flood = [("peer", f"10.1.{n // 256}.{n % 256}") for n in range(BACKOFF_ENTRIES + 10)]
    door.failed(*flood)
    other = Backoff(lambda: now[0], state_dir=tmp_path)
    other.wait_s(USER)
    assert len(other._table) == BACKOFF_ENTRIES and flood[0] not in other._table
    for _ in range(20):
        door.failed(USER)
    now[0] -= 3600  # the wall clock set back an hour
    assert other.wait_s(USER) == 60.0


def _fail_many(state: str, times: int) -> None:
    door = Backoff(state_dir=state)
    for _ in range(times):
        door.failed(("user", "shared"))


def test_processes_failing_at_once_lose_no_count(tmp_path: Path) -> None:
    context = multiprocessing.get_context("spawn")
    workers = [context.Process(target=_fail_many, args=(str(tmp_path), 30)) for _ in range(3)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join(60)
        assert worker.exitcode == 0
    rows = json.loads((tmp_path / BACKOFF_FILE).read_bytes())["entries"]
    assert [row[2] for row in rows if row[:2] == ["user", "shared"]] == [90]


@pytest.mark.parametrize("garbage", [b"\x00\x17\xff", b"{}", b'{"entries": [[1, 2]]}', b"[]"])
def test_a_corrupt_table_is_one_log_line_and_an_empty_table(
        tmp_path: Path, garbage: bytes, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / BACKOFF_FILE
    path.write_bytes(garbage)
    door = Backoff(state_dir=tmp_path)
    with caplog.at_level(logging.WARNING, logger="softplc.security.backoff"):
        assert door.wait_s(USER, PEER) == 0
        assert door.wait_s(USER) == 0
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and str(path) in lines[0] and "empty" in lines[0]
    for _ in range(FREE_FAILURES + 1):
        door.failed(USER)
    assert Backoff(state_dir=tmp_path).wait_s(USER) > 0  # written again, whole


# -- through the real doors --------------------------------------------------------------


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[tuple[int, str]]:
    """`softplc run` with HTTP and OPC UA on one state directory holding op and view."""
    store = UserStore(tmp_path / "state")
    store.add("op", Role.OPERATOR, "operator-password")
    store.add("view", Role.VIEWER, "viewer-password")
    api, opcua = free_port(), free_port()
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--start", "--api",
                      f"127.0.0.1:{api}", "--modbus", "off", "--opcua", f"127.0.0.1:{opcua}",
                      "--state-dir", "state", "--quiet", "--period", "10ms"],
                     lambda: call(f"http://127.0.0.1:{api}", "GET", "/api/v1/status",
                                  timeout_s=5).status == 200,
                     cwd=tmp_path, stdout=subprocess.DEVNULL, what="softplc run answering"):
        yield api, f"opc.tcp://127.0.0.1:{opcua}"


def _wrong_password(port: int, name: str) -> int:
    """A wrong password for `name` over HTTP Basic, from 127.0.0.2: not the OPC UA client's
    address, so that only the user name is shared between the doors."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30,
                                            source_address=("127.0.0.2", 0))
    pair = base64.b64encode(f"{name}:not-the-password".encode()).decode()
    try:
        connection.request("POST", "/api/v1/stop", headers={"Authorization": f"Basic {pair}"})
        return connection.getresponse().status
    finally:
        connection.close()


async def _opcua_login(url: str, name: str, password: str) -> int:
    """The status code of an OPC UA session activated as `name` (0: Good)."""
    client = patient_client(url)
    client.set_user(name)
    client.set_password(password)
    try:
        async with client:
            return 0
    except ua.UaStatusCodeError as exc:
        return int(exc.code)


def test_wrong_passwords_over_http_refuse_an_opcua_login_of_that_name(
        plc: tuple[int, str], tmp_path: Path) -> None:
    api, opcua = plc
    # Sent at once, they all pass the check before the first fails (one scrypt at a time):
    # eight failures close the name for 16 s, longer than an OPC UA connection takes.
    with ThreadPoolExecutor(8) as pool:
        answers = list(pool.map(lambda _: _wrong_password(api, "op"), range(8)))
    assert answers.count(401) >= FREE_FAILURES + 3, answers  # closed >= 4 s
    assert Backoff(state_dir=tmp_path / "state").wait_s(("user", "op")) > 2.0
    refused = asyncio.run(_opcua_login(opcua, "op", "operator-password"))
    assert refused == ua.StatusCodes.BadUserAccessDenied  # the right password, unchecked
    assert asyncio.run(_opcua_login(opcua, "view", "viewer-password")) == 0  # same address
    (tmp_path / "state" / BACKOFF_FILE).unlink()  # every closure lifted, at every door
    assert asyncio.run(_opcua_login(opcua, "op", "operator-password")) == 0
