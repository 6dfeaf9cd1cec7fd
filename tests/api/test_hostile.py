"""Hostile and careless HTTP clients (issue 28), over real sockets on 127.0.0.1.

Each case checks the refusal, and that the neighbours (GET /status, POST /stop and a Modbus
read from a slave on the same event loop, as in the communication process) still answer,
within a bound taken from the same test's idle measurement. Counts and waits are bounded.
"""

from __future__ import annotations

import logging
import resource
import socket
import statistics
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import pytest

from softplc.api.limits import Capacity, HttpLimits
from softplc.core.image import ImageSizes
from softplc.hmi.server import ModbusSlave
from tests.api.conftest import Plc, ServerThread, make_server
from tests.api.helpers import ANSWER_WITHIN_S, TRANSPORT, call, owner_headers
from tests.api.test_limits import closed_by_peer, connect, get, parse, read_all
from tests.support import eventually, wait_until

ROOT = Path(__file__).resolve().parents[2]
SLOWER = 10  # under abuse, the median of a neighbour's answers within 10x its idle worst
ROUNDS = 5
FC3_READ = struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 10)  # 10 holding registers from 0


@dataclass
class Door:
    """The API and a Modbus slave on one asyncio loop, in front of a scan thread."""

    api: ServerThread
    modbus_port: int

    @property
    def url(self) -> str:
        return self.api.url


@contextmanager
def door(plc: Plc, state_dir: Path, **kwargs: object) -> Iterator[Door]:
    with make_server(plc, state_dir, **kwargs) as api:
        slave = ModbusSlave(plc.reader, plc.channel.send_hmi_write, sizes=ImageSizes(), port=0)
        api.call(slave.start())
        try:
            yield Door(api, slave.bound_port)
        finally:
            api.call(slave.stop())


def timed(action: Callable[[], int]) -> tuple[int, float]:
    began = time.monotonic()
    status = action()
    return status, time.monotonic() - began


def modbus_read(port: int) -> int:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
        sock.sendall(FC3_READ)
        reply = sock.recv(4096)
    return 200 if reply[7:8] == b"\x03" and len(reply) == 9 + 20 else 500


def neighbours(d: Door, headers: dict[str, str] | None = None
               ) -> dict[str, Callable[[], int]]:
    h = headers or owner_headers(d.url)
    return {"status": lambda: call(d.url, "GET", "/api/v1/status", None, h, 5).status,
            "stop": lambda: call(d.url, "POST", "/api/v1/stop", None, h, 5).status,
            "modbus": lambda: modbus_read(d.modbus_port)}


def measure(probes: dict[str, Callable[[], int]]) -> dict[str, list[tuple[int, float]]]:
    return {name: [timed(probe) for _ in range(ROUNDS)] for name, probe in probes.items()}


def assert_neighbours_answer(idle: dict[str, list[tuple[int, float]]],
                             probes: dict[str, Callable[[], int]]) -> None:
    """Every probe answers (stop: applied or refused, never 503), the median within SLOWER
    times the worst idle answer of the same probe."""
    loaded = measure(probes)
    for name, samples in loaded.items():
        assert all(status in (200, 409) for status, _ in samples), (name, samples)
        bound_s = SLOWER * max(seconds for _, seconds in idle[name])
        median_s = statistics.median(seconds for _, seconds in samples)
        assert median_s <= bound_s, (name, median_s, bound_s)


def started(d: Door) -> None:
    program = TRANSPORT.read_text()
    assert call(d.url, "POST", "/api/v1/program?name=transport.yaml", program,
                timeout_s=ANSWER_WITHIN_S, owner=True).status == 200  # the server's time to answer
    eventually(lambda: call(d.url, "GET", "/api/v1/symbols").body["symbols"])


def sse_request(path: str = "/api/v1/events") -> bytes:
    return f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode()


def status_line(sock: socket.socket) -> bytes:
    """The response head, or b"" for a connection evicted before it was answered."""
    data = b""
    while b"\r\n\r\n" not in data:
        try:
            chunk = sock.recv(4096)
        except ConnectionResetError:
            return b""
        if not chunk:
            break
        data += chunk
    return data


def test_300_event_streams_leave_stop_status_and_modbus_served(
        plc_parts: Plc, scan: object, tmp_path: Path) -> None:
    with door(plc_parts, tmp_path / "state") as d, ExitStack() as stack:
        probes = neighbours(d)
        idle = measure(probes)
        capacity = d.api.server.bounds.capacity
        socks = [stack.enter_context(connect(d.api.server.bound_port, 10)) for _ in range(300)]
        for sock in socks:
            sock.sendall(sse_request())
        heads = [status_line(sock) for sock in socks]
        accepted = [h for h in heads if h.startswith(b"HTTP/1.1 200")]
        refused = [h for h in heads if h.startswith(b"HTTP/1.1 503")]
        # All from one address: its share of the pool, not the whole process.
        assert len(accepted) == capacity.streams_per_peer < capacity.connections
        assert len(accepted) + len(refused) + sum(h == b"" for h in heads) == 300
        assert refused and b'"too many events streams from 127.0.0.1' in refused[0]
        assert_neighbours_answer(idle, probes)
        assert call(d.url, "GET", "/").status == 200  # the page too
        report = call(d.url, "GET", "/api/v1/status").body["http"]
        assert report["streams"] == {"events": len(accepted)}
        assert report["streams_refused"] >= len(refused)
        # The page's live stream has a pool of its own: open event streams do not blank it.
        with connect(d.api.server.bound_port) as page:
            page.sendall(sse_request("/api/v1/live"))
            assert status_line(page).startswith(b"HTTP/1.1 200")


def test_ordinary_requests_held_open_cannot_take_the_reserve(
        plc_parts: Plc, scan: object, tmp_path: Path) -> None:
    limits = HttpLimits(max_connections=16)
    with door(plc_parts, tmp_path / "state", limits=limits) as d, ExitStack() as stack:
        started(d)
        probes = neighbours(d)
        idle = measure(probes)
        ordinary = d.api.server.bounds.capacity.ordinary
        held = []
        owner = owner_headers(d.url)["Authorization"].encode()  # an operator's write
        for _ in range(16):  # bodies that never arrive: each request stays in the app
            sock = stack.enter_context(connect(d.api.server.bound_port))
            sock.sendall(b"PUT /api/v1/symbols/hold HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                         b"Authorization: " + owner + b"\r\n"
                         b"Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{")
            held.append(sock)
        assert wait_until(lambda: d.api.server.bounds.report()["busy_refused"] == 16 - ordinary)
        assert d.api.server.bounds.report()["ordinary_in_progress"] == ordinary < 16
        assert_neighbours_answer(idle, probes)
        assert get(d.api.server.bound_port, "/")[0] == 200


def test_idle_connections_that_never_authenticated_are_evicted_first(
        plc_parts: Plc, scan: object, tmp_path: Path) -> None:
    limits = HttpLimits(max_connections=16)
    with door(plc_parts, tmp_path / "state", limits=limits, token_required=True) as d, \
            ExitStack() as stack:
        token = (tmp_path / "state" / "api_token").read_text().strip()
        auth = {"Authorization": f"Bearer {token}", "Host": "127.0.0.1"}
        port = d.api.server.bound_port
        operator = stack.enter_context(connect(port))
        head = "GET /api/v1/status HTTP/1.1\r\n" + "".join(
            f"{k}: {v}\r\n" for k, v in auth.items()) + "\r\n"
        operator.sendall(head.encode())
        assert status_line(operator).startswith(b"HTTP/1.1 200")
        time.sleep(0.05)  # the operator's connection is now the one idle longest
        junk = [stack.enter_context(connect(port)) for _ in range(40)]
        wrong = stack.enter_context(connect(port))
        wrong.sendall(b"GET /api/v1/status HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert status_line(wrong).startswith(b"HTTP/1.1 401")
        assert wait_until(lambda: d.api.server.bounds.stats.evicted >= 40 + 1 - 15)
        operator.sendall(head.encode())  # still open: the junk went first
        assert status_line(operator).startswith(b"HTTP/1.1 200")
        assert sum(closed_by_peer(sock) for sock in junk[:24]) == 24


BOMBS = {
    "100,000-deep [": b"[" * 100_000,
    '50,000-deep {"value":': b'{"value":' * 50_000,
    "500,000-digit integer": b'{"value": ' + b"9" * 500_000 + b"}",
    "4,000-deep [": b"[" * 4_000,  # the same bombs under the size limit: refused by shape
    '400-deep {"value":': b'{"value":' * 400,
    "4,000-digit integer": b'{"value": ' + b"9" * 4000 + b"}",
    "40-deep [": b'{"value": ' + b"[" * 40 + b"]" * 40 + b"}",
}


@pytest.mark.parametrize("route", ["symbols", "forces"])
def test_json_bombs_are_one_line_4xx_and_never_a_traceback(
        plc_parts: Plc, scan: object, tmp_path: Path, route: str,
        caplog: pytest.LogCaptureFixture) -> None:
    with door(plc_parts, tmp_path / "state") as d:
        started(d)
        probes = neighbours(d)
        idle = measure(probes)
        stop = threading.Event()
        answers: list[tuple[str, int, bytes]] = []

        def bombard() -> None:
            while not stop.is_set():
                for what, bomb in BOMBS.items():
                    answer = call(d.url, "PUT", f"/api/v1/{route}/hold", bomb,
                                  {"Content-Type": "application/json"}, 10, owner=True)
                    answers.append((what, answer.status, answer.raw))
                    # Paced: the bombs' client shares this process (and its GIL) with the
                    # server and the probes; unpaced it measures the GIL, not the server.
                    stop.wait(0.005)

        caplog.set_level(logging.INFO)
        thread = threading.Thread(target=bombard, daemon=True)
        thread.start()
        try:
            assert wait_until(lambda: len(answers) >= len(BOMBS))
            assert_neighbours_answer(idle, probes)
        finally:
            stop.set()
            thread.join(30)
        for what, status, raw in answers:
            assert status in (400, 413), (what, status, raw[:200])
            assert b"\n" not in raw and len(raw) < 300, (what, raw[:300])
        by_bomb = {what: raw for what, _, raw in answers}
        assert b"line 1, column 33" in by_bomb["4,000-deep ["]
        assert b"has 4000 characters" in by_bomb["4,000-digit integer"]
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]


# --- file descriptors: the limit the process really has ------------------------------------


def test_capacity_follows_the_descriptor_limit() -> None:
    limits = HttpLimits()
    assert Capacity.of(limits, 2, 20_000, 50).connections == 128
    small = Capacity.of(limits, 2, 256, 56)  # a quarter of the 200 free descriptors
    assert small.connections == 50
    assert small.reserve >= 1 and small.ordinary >= 1
    assert 2 * small.streams + small.ordinary + small.reserve <= small.connections


def _low_nofile() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (160, resource.getrlimit(
        resource.RLIMIT_NOFILE)[1]))


def test_a_flood_under_a_low_descriptor_limit_never_exhausts_the_process() -> None:
    """`ulimit -n 160`: the cap follows, so accept() never fails and nothing is logged per
    connection; a plain GET is served at the first try during the flood."""
    proc = subprocess.Popen([sys.executable, "-m", "tests.api.limits_server", "4.0"], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_low_nofile)
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline())
        with ExitStack() as stack:
            for _ in range(400):
                sock = stack.enter_context(connect(port))
                with suppress(OSError):
                    sock.send(b"GET / HTTP/1.1\r\n")
            assert get(port) == (200, b"ok")
    finally:
        try:  # closes its stdin: the server ends
            _, stderr = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, stderr = proc.communicate(timeout=5)
    assert "out of system resource" not in stderr and "Too many open files" not in stderr, \
        stderr[-2000:]
    assert stderr.count("\n") <= 2, stderr[-2000:]  # a summary line, not one per connection


def test_the_refusal_itself_is_not_logged_per_connection(caplog: pytest.LogCaptureFixture
                                                         ) -> None:
    from tests.api.test_limits import served

    caplog.set_level(logging.DEBUG, logger="softplc.api.limits")
    with served(max_connections=2) as server, ExitStack() as stack:
        for _ in range(2):
            sock = stack.enter_context(connect(server.port))
            sock.sendall(b"GET /wait HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert wait_until(lambda: server.inside == 2)
        for _ in range(20):
            with connect(server.port) as refused:
                assert parse(read_all(refused))[0] == 503
        assert server.bounds.stats.refused == 20
        lines = [r for r in caplog.records if r.name == "softplc.api.limits"]
        assert len(lines) == 1 and "refused 20" not in lines[0].getMessage()
        assert "refused 1" in lines[0].getMessage()
