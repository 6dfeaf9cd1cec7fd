"""Modbus fuzz against `softplc run` as production runs it: the scan in one process, the
Modbus slave in the communication process. While random frames, a connection flood and a
client that never reads hit the slave, the scan keeps running; its overruns and p99
lateness before and after are recorded (never asserted: the machine is shared and noisy)."""

from __future__ import annotations

import contextlib
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.core.lifecycle import PlcState
from softplc.hmi.map import (
    STATUS_OVERRUNS,
    STATUS_P99_LATENESS_US,
    STATUS_SCAN_COUNT,
    STATUS_STATE,
    STATUS_WORDS,
)
from tests.fuzz import budget
from tests.fuzz.frames import mbap, random_pdu
from tests.hmi.helpers import connect, recv_adu, request
from tests.support import free_port

ROOT = Path(__file__).resolve().parents[2]
STATUS_READ = bytes([4]) + (1024).to_bytes(2, "big") + STATUS_WORDS.to_bytes(2, "big")


@pytest.fixture
def plc_port(tmp_path: Path) -> Iterator[int]:
    port = free_port()
    log = tmp_path / "stderr.txt"
    with log.open("w") as stderr:  # a file, not a pipe: a log flood must not block the PLC
        proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
             "--modbus", f"127.0.0.1:{port}",
             "--opcua", "off", "--api", "off", "--state-dir", str(tmp_path),
             "--quiet", "--period", "10ms"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=stderr, text=True)
    try:
        deadline = time.monotonic() + 40  # two processes start slowly on a loaded machine
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            assert proc.poll() is None, log.read_text()
            time.sleep(0.1)
        yield port
        # one line per frame (asyncio's "socket.send() raised exception.") was a log flood
        assert log.read_text().count("\n") < 50, log.read_text()[-2000:]
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


def _u32(words: list[int], offset: int) -> int:
    return (words[offset] << 16) | words[offset + 1]


def status(port: int) -> dict[str, int]:
    with connect(port) as sock:
        reply = request(sock, STATUS_READ)
    words = [int.from_bytes(reply[2 + 2 * i : 4 + 2 * i], "big") for i in range(STATUS_WORDS)]
    return {"state": words[STATUS_STATE], "scans": _u32(words, STATUS_SCAN_COUNT),
            "overruns": _u32(words, STATUS_OVERRUNS),
            "p99_lateness_us": _u32(words, STATUS_P99_LATENESS_US)}


def _random_frames(port: int, rng: random.Random, batches: int) -> int:
    sent = 0
    for _ in range(batches):
        pdus = [random_pdu(rng) for _ in range(50)]
        with connect(port) as sock:
            sock.sendall(b"".join(mbap(p, i, 1) for i, p in enumerate(pdus)))
            for i, pdu in enumerate(pdus):
                tid, _, _, reply = recv_adu(sock)
                assert tid == i
                assert reply[0] == pdu[0] or reply[1:] in (b"\1", b"\2", b"\3"), reply.hex()
        sent += len(pdus)
    return sent


def _flood(port: int, n: int) -> int:
    socks = [connect(port) for _ in range(n)]
    try:
        return sum(_closed_at_once(s) for s in socks)
    finally:
        for s in socks:
            s.close()


def _closed_at_once(sock: socket.socket) -> bool:
    sock.settimeout(0.5)
    try:
        return sock.recv(1) == b""
    except TimeoutError:
        return False
    except ConnectionResetError:
        return True


def _non_reader(port: int, n: int, seconds: float) -> None:
    burst = b"".join(mbap(bytes.fromhex("030000007d"), i & 0xFFFF, 1) for i in range(n))
    hog = connect(port, timeout_s=10)
    sender = threading.Thread(target=_send_quietly, args=(hog, burst), daemon=True)
    sender.start()
    time.sleep(seconds)
    hog.close()
    sender.join(10)


def _send_quietly(sock: socket.socket, data: bytes) -> None:
    with contextlib.suppress(OSError):  # closed while blocked: that is the point
        sock.sendall(data)


def test_the_scan_keeps_running_while_the_slave_is_fuzzed(plc_port: int) -> None:
    deadline = time.monotonic() + 30
    while (before := status(plc_port))["state"] != PlcState.RUNNING:
        assert time.monotonic() < deadline, before
        time.sleep(0.1)
    rng = random.Random(budget.seed(4711))
    started = time.monotonic()
    frames = _random_frames(plc_port, rng, budget.scaled(10))
    refused = _flood(plc_port, 40)  # the default limit is 16
    _non_reader(plc_port, budget.scaled(20_000), 1.0)
    frames += _random_frames(plc_port, rng, budget.scaled(2))
    after = status(plc_port)
    assert after["state"] == PlcState.RUNNING
    assert after["scans"] > before["scans"]
    assert refused >= 40 - 16
    budget.record("modbus.process", frames=frames, flood_connections=40,
                  flood_refused=refused, fuzz_seconds=round(time.monotonic() - started, 1),
                  scans=after["scans"] - before["scans"],
                  overruns=after["overruns"] - before["overruns"],
                  p99_lateness_us_before=before["p99_lateness_us"],
                  p99_lateness_us_after=after["p99_lateness_us"])
