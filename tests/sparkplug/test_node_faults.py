"""The edge node and its door when something is wrong, in this process against a real
Mosquitto: a STATE whose timestamp is Infinity or whose online is a string (retained: it must
not end the process, which would restart into the same message), a state dir where the bdSeq
file cannot be written (the node still births, and a new CONNECT still gets the next bdSeq), an
NCMD that arrives before the first NBIRTH (refused and audited, not dropped), and commands
refused because the door's queue was full (audited too)."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import (
    CommandReply,
    CommandRequest,
    HmiWrite,
    Snapshot,
    SnapshotUnavailable,
)
from softplc.security.audit import AuditTrail
from softplc.security.roles import Role
from softplc.sparkplug.codec import BOOLEAN, STRING, Metric, Payload, decode, encode
from softplc.sparkplug.config import SparkplugConfig
from softplc.sparkplug.door import MAX_WAITING, Door
from softplc.sparkplug.metrics import Report
from softplc.sparkplug.node import EdgeNode, Reading
from tests.sparkplug.conftest import Broker, Host

BOARD: Mapping[str, Any] = {"program_hash": "h1", "program": "p", "symbols": {}}


def _read() -> Reading:
    return BOARD, None


def _steps(node: EdgeNode, until: Callable[[], bool], limit_s: float = 20.0) -> bool:
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        node.step(0.02)
        if until():
            return True
    return False


def _bdseq(host: Host, start: int) -> list[int]:
    return [decode(m.payload).metrics[0].value  # type: ignore[misc]
            for _, m in host.since(start, "NBIRTH")]


def test_bad_state_and_an_early_ncmd(tmp_path: Path, mosquitto: Callable[..., Broker],
                                     host: Callable[..., Host]) -> None:
    broker = mosquitto()
    h = host(broker.port)
    h.send("spBv1.0/STATE/scada1", b'{"online": false, "timestamp": Infinity}', qos=1,
           retain=True)
    got: list[tuple[Report | None, Metric]] = []
    config = SparkplugConfig("127.0.0.1", broker.port, "plant", "n1", primary_host="scada1",
                             state_dir=str(tmp_path))
    node = EdgeNode(config, _read, lambda report, metric: got.append((report, metric)))
    try:
        # the retained STATE is read (and ignored) once subscribed; the node waits on
        assert _steps(node, lambda: node.subscribed)
        _steps(node, lambda: False, 0.3)
        h.send("spBv1.0/plant/NCMD/n1", encode(Payload(1, (Metric("x", STRING, "v"),))))
        assert _steps(node, lambda: bool(got))
        assert got[0][0] is None and got[0][1].name == "x"  # to the door, before any birth
        h.send("spBv1.0/STATE/scada1", b'{"online": "true", "timestamp": 4}', qos=1, retain=True)
        _steps(node, lambda: False, 0.5)
        assert not node.born  # a string is no boolean: the message is ignored, not "online"
        h.send("spBv1.0/STATE/scada1", json.dumps({"online": True, "timestamp": 5}).encode(),
               qos=1, retain=True)
        assert _steps(node, lambda: node.born)
    finally:
        node.close()


def test_a_bdseq_file_that_cannot_be_written(tmp_path: Path,
                                             mosquitto: Callable[..., Broker],
                                             host: Callable[..., Host]) -> None:
    broker = mosquitto()
    h = host(broker.port)
    (tmp_path / "sparkplug").write_text("a file where the folder should be\n")
    config = SparkplugConfig("127.0.0.1", broker.port, "plant", "n2", state_dir=str(tmp_path))
    node = EdgeNode(config, _read, lambda report, metric: None)
    try:
        assert _steps(node, lambda: bool(h.since(0, "NBIRTH")))
        assert node.keep_failed
        node.close()  # a new CONNECT: the next bdSeq although the file still cannot be kept
        mark = h.count()
        assert _steps(node, lambda: bool(h.since(mark, "NBIRTH")))
        assert _bdseq(h, 0) == [0, 1]
    finally:
        node.close()


class _SlowPlc:
    """The PLC side of the channel, answering a program command only when released."""

    def __init__(self) -> None:
        self.release = threading.Event()

    def send_hmi_write(self, write: HmiWrite) -> None:
        raise AssertionError("no write expected")

    def send_command(self, request: CommandRequest, timeout_s: float = 5.0) -> CommandReply:
        self.release.wait(10)
        return CommandReply(request.id, True, "ok", PlcState.STOPPED)


class _NoSnapshot:
    def latest(self) -> Snapshot:
        raise SnapshotUnavailable("none in this test")


def _trail(state: Path) -> list[dict[str, Any]]:
    return [json.loads(x) for x in (state / "audit.jsonl").read_text().splitlines()]


def test_the_door_audits_what_it_refuses_without_a_birth_or_when_busy(tmp_path: Path) -> None:
    plc = _SlowPlc()
    config = SparkplugConfig("127.0.0.1", 1, "plant", "n3", role=Role.ENGINEER, commands=True,
                             state_dir=str(tmp_path))
    door = Door(config, plc, _NoSnapshot(), AuditTrail(tmp_path))
    try:
        door.submit(None, Metric("fill_to", None, 3.0))
        door.submit(None, Metric(None, None, 3.0))
        lines: list[str] = []
        deadline = time.monotonic() + 10
        while len(lines) < 2 and time.monotonic() < deadline:
            lines += door.outcomes()
            time.sleep(0.01)
        # one command holds the worker; the queue fills; more are refused
        for _ in range(MAX_WAITING + 4):
            door.submit(None, Metric("Node Control/Command", STRING, "stop"))
        assert door.refused_busy >= 3
        plc.release.set()
    finally:
        door.close()
    records = _trail(tmp_path)
    assert [(r["outcome"], r["status"]) for r in records[:2]] == [
        ("refused", "no NBIRTH yet: fill_to is not known"),
        ("refused", "the metric has no name and no alias")]
    busy = [r for r in records if r["detail"].get("refused")]
    assert sum(r["detail"]["refused"] for r in busy) == door.refused_busy
    assert len(records) == 2 + (MAX_WAITING + 4 - door.refused_busy) + len(busy)


def _publish_packet(topic: str, payload: bytes) -> bytes:
    body = len(topic).to_bytes(2, "big") + topic.encode() + payload
    size, length = len(body), bytearray()
    while True:
        byte, size = size & 0x7F, size >> 7
        length.append(byte | (0x80 if size else 0))
        if not size:
            return b"\x30" + bytes(length) + body


def test_rebirths_asked_while_the_broker_does_not_read_are_not_queued(tmp_path: Path) -> None:
    """A broker that stops reading (a raw socket here, answering CONNACK and SUBACK) while a
    host keeps asking for Rebirth: once the socket holds unsent bytes, no birth is queued on
    top (paho's QoS 0 queue is unbounded: each NBIRTH holds every metric)."""
    symbols = {f"s{i:04}": {"type": "real", "address": f"%MD{i}", "direction": "memory"}
               for i in range(400)}
    board = {"program_hash": "h1", "program": "p", "symbols": symbols}
    listener = socket.create_server(("127.0.0.1", 0))
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    config = SparkplugConfig("127.0.0.1", listener.getsockname()[1], "plant", "n4",
                             state_dir=str(tmp_path))
    node = EdgeNode(config, lambda: (board, None), lambda report, metric: None)
    try:
        node.step(0.02)  # CONNECT
        conn, _ = listener.accept()
        conn.settimeout(5)
        conn.recv(4096)
        conn.sendall(b"\x20\x02\x00\x00")  # CONNACK accepted
        assert _steps(node, lambda: node.connected, 5)
        _steps(node, lambda: False, 0.2)  # the SUBSCRIBE goes out
        subscribe = conn.recv(4096)
        conn.sendall(b"\x90\x03" + subscribe[2:4] + b"\x01")  # SUBACK, QoS 1
        assert _steps(node, lambda: node.born, 5)
        assert node.client is not None
        node.client.socket().setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        rebirth = _publish_packet("spBv1.0/plant/NCMD/n4", encode(Payload(1, (
            Metric("Node Control/Rebirth", BOOLEAN, True),))))
        blocked_at = None
        for _ in range(300):  # the broker reads nothing more
            conn.sendall(rebirth)
            node.step(0.005)
            assert node.client is not None
            if blocked_at is None and node.client.want_write():
                blocked_at = node.counts["births"]
        assert blocked_at is not None, "the socket never filled"
        assert node.counts["births"] <= blocked_at + 1
        conn.close()
    finally:
        node.client = None
        listener.close()


def test_no_write_when_the_snapshot_cannot_be_read(tmp_path: Path) -> None:
    """As the Modbus slave refuses a write it cannot check against the running program, so does
    this door (it wrote without the check)."""
    board = {"program_hash": "h1", "program": "p",
             "symbols": {"fill_to": {"type": "real", "address": "%MD1", "direction": "memory"}}}
    config = SparkplugConfig("127.0.0.1", 1, "plant", "n5", role=Role.ENGINEER,
                             state_dir=str(tmp_path))
    door = Door(config, _SlowPlc(), _NoSnapshot(), AuditTrail(tmp_path))
    try:
        door.submit(Report(board, 0.0), Metric("fill_to", None, 3.0))
        deadline = time.monotonic() + 10
        lines: list[str] = []
        while not lines and time.monotonic() < deadline:
            lines += door.outcomes()
            time.sleep(0.01)
    finally:
        door.close()
    assert [(r["outcome"], r["status"]) for r in _trail(tmp_path)] == [
        ("refused", "the PLC's snapshot cannot be read: nothing is written")]
