"""Server-sent events fed from a hand-published status board: each new event once."""

from __future__ import annotations

import http.client
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api import events as events_module
from softplc.api.client import ApiClient
from tests.api.conftest import Plc, ServerThread, make_server


def _event(seq: int, name: str) -> dict[str, Any]:
    return {"seq": seq, "scan": seq * 10, "t_ns": seq * 1000, "name": name}


class Board:
    """What the scan process would publish: the last events, seq increasing."""

    def __init__(self, plc: Plc) -> None:
        self.plc = plc
        self.events: list[dict[str, Any]] = []

    def add(self, *names: str) -> None:
        for name in names:
            self.events.append(_event(len(self.events) + 1, name))
        self.plc.board.publish({"state": "RUNNING", "scan_count": len(self.events),
                                "events": self.events[-256:]})


class Stream:
    """A raw SSE reader: lines from GET /api/v1/events."""

    def __init__(self, api: ServerThread, query: str = "", **headers: str) -> None:
        self.conn = http.client.HTTPConnection("127.0.0.1", api.server.bound_port, timeout=5)
        self.conn.request("GET", f"/api/v1/events{query}", headers=headers)
        self.response = self.conn.getresponse()
        self.pending = b""
        assert self.response.status == 200
        assert self.response.getheader("Content-Type", "").startswith("text/event-stream")
        assert self.readline() == "retry: 1000"

    def readline(self) -> str:
        while b"\n" not in self.pending:
            chunk = self.response.read1(65536)  # readline would wait for further chunks
            if not chunk:
                raise EOFError("the stream ended")
            self.pending += chunk
        line, _, self.pending = self.pending.partition(b"\n")
        return line.decode()

    def next_block(self) -> list[str]:
        lines: list[str] = []
        while True:
            line = self.readline()
            if not line and lines:
                return lines
            if line:
                lines.append(line)

    def next_events(self, count: int) -> list[dict[str, Any]]:
        found: list[dict[str, Any]] = []
        while len(found) < count:
            block = self.next_block()
            found += [json.loads(line[6:]) for line in block if line.startswith("data: ")
                      and not any(b.startswith("event:") for b in block)]
        return found

    def silent_for(self, seconds: float) -> list[str]:
        """Every line but comments (heartbeats) received within `seconds`."""
        assert self.conn.sock is not None
        deadline = time.monotonic() + seconds
        got: list[str] = []
        try:
            while (left := deadline - time.monotonic()) > 0:
                self.conn.sock.settimeout(left)
                line = self.readline()
                if line and not line.startswith(":"):
                    got.append(line)
        except (TimeoutError, OSError, EOFError):
            pass
        return got

    def close(self) -> None:
        self.conn.close()


@pytest.fixture
def sse(plc_parts: Plc, tmp_path: Path) -> Iterator[tuple[ServerThread, Board]]:
    board = Board(plc_parts)
    board.add("old_a", "old_b")
    with make_server(plc_parts, tmp_path, heartbeat_s=0.3) as api:
        yield api, board


def test_new_events_are_delivered_once_each(sse: tuple[ServerThread, Board]) -> None:
    api, board = sse
    stream = Stream(api)
    try:
        # Stream() has read the stream's first line: the subscription (made before
        # it) has read the board, old_a and old_b are history.
        board.add("a", "b")
        first = stream.next_events(2)
        assert [(e["seq"], e["name"]) for e in first] == [(3, "a"), (4, "b")]
        board.add("c")  # the board still holds a and b: they must not come again
        assert [e["name"] for e in stream.next_events(1)] == ["c"]
        board.add("d")
        assert [e["name"] for e in stream.next_events(1)] == ["d"]
        assert stream.silent_for(0.4) == []
    finally:
        stream.close()


def test_event_lines_carry_the_seq_as_id(sse: tuple[ServerThread, Board]) -> None:
    api, board = sse
    stream = Stream(api)
    try:
        board.add("x")
        block = stream.next_block()
        while block[0].startswith(":"):
            block = stream.next_block()
        assert block[0] == "id: 3"
        assert json.loads(block[1][6:]) == _event(3, "x")
    finally:
        stream.close()


def test_names_filter(sse: tuple[ServerThread, Board]) -> None:
    api, board = sse
    stream = Stream(api, "?names=b,d")
    try:
        board.add("a", "b", "c", "d", "e")
        assert [e["name"] for e in stream.next_events(2)] == ["b", "d"]
        assert stream.silent_for(0.4) == []
    finally:
        stream.close()


def test_last_event_id_replays_what_the_board_still_holds(sse: tuple[ServerThread, Board]
                                                           ) -> None:
    api, _ = sse
    stream = Stream(api, **{"Last-Event-ID": "1"})
    try:
        assert [e["name"] for e in stream.next_events(1)] == ["old_b"]
    finally:
        stream.close()


def test_heartbeat_comment(sse: tuple[ServerThread, Board]) -> None:
    api, _ = sse
    stream = Stream(api)
    try:
        lines = [stream.readline() for _ in range(4)]
        assert ": heartbeat" in lines
    finally:
        stream.close()


def test_several_clients_each_get_every_event(sse: tuple[ServerThread, Board]) -> None:
    api, board = sse
    streams = [Stream(api) for _ in range(3)]
    try:
        board.add("p", "q")
        for stream in streams:
            assert [e["name"] for e in stream.next_events(2)] == ["p", "q"]
    finally:
        for stream in streams:
            stream.close()


def test_api_client_reads_the_stream(sse: tuple[ServerThread, Board]) -> None:
    api, board = sse
    # From seq 2 on: z comes live once the stream is open, or (on a slow machine, where the
    # timer can beat the subscription) from the board's replay; once either way.
    events = ApiClient(api.url, timeout_s=5).events(names=["z"], last_id=2)
    timer = threading.Timer(0.5, lambda: board.add("y", "z"))
    timer.start()
    try:
        first = next(events)
    finally:
        timer.join()
        events.close()
    assert first == _event(4, "z")


def test_a_slow_client_loses_the_oldest_events_and_is_told(monkeypatch: pytest.MonkeyPatch
                                                            ) -> None:
    monkeypatch.setattr(events_module, "EVENT_QUEUE", 3)
    sub = events_module.Subscriber(frozenset(), after=0)
    for seq in range(1, 6):
        sub.offer(_event(seq, "e"))
    sub.offer(_event(5, "e"))  # seen already
    assert sub.dropped == 2
    kept = [sub.queue.get_nowait() for _ in range(sub.queue.qsize())]
    assert [e["seq"] for e in kept if e] == [3, 4, 5]


def test_bad_last_event_id_is_400(sse: tuple[ServerThread, Board]) -> None:
    api, _ = sse
    conn = http.client.HTTPConnection("127.0.0.1", api.server.bound_port, timeout=5)
    try:
        conn.request("GET", "/api/v1/events", headers={"Last-Event-ID": "abc"})
        assert conn.getresponse().status == 400
    finally:
        conn.close()


def test_streams_end_when_the_server_stops(plc_parts: Plc, tmp_path: Path) -> None:
    board = Board(plc_parts)
    board.add("a")
    handle = make_server(plc_parts, tmp_path, heartbeat_s=10)
    with handle as api:
        stream = Stream(api)
        started = time.monotonic()
    assert time.monotonic() - started < 5
    assert stream.conn.sock is not None
    stream.conn.sock.settimeout(2)
    try:
        with pytest.raises(EOFError):
            while True:
                assert not stream.readline().startswith("data:")
    finally:
        stream.close()


def test_events_beyond_what_the_board_holds_are_reported(sse: tuple[ServerThread, Board]
                                                          ) -> None:
    api, board = sse
    stream = Stream(api)
    try:
        board.add(*[f"e{i}" for i in range(300)])  # seq 3..302; the board keeps the last 256
        block = stream.next_block()
        while block[0].startswith(":"):
            block = stream.next_block()
        assert block == ["event: overflow", 'data: {"dropped": 44}']
        received = stream.next_events(256)
        assert [e["seq"] for e in received] == list(range(47, 303))
    finally:
        stream.close()
