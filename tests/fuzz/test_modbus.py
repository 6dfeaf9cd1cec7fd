"""Modbus fuzz against the real ModbusSlave on 127.0.0.1 (port 0): random and mutated
frames checked against the spec (tests/fuzz/oracle.py), broken byte streams, connection
floods, stalled and non-reading clients. After each batch a well-formed request must get
the right answer. Counts scale with SOFTPLC_FUZZ_SCALE; every wait is bounded."""

from __future__ import annotations

import contextlib
import random
import socket
import struct
import threading
import time
from collections.abc import Iterator

import pytest

from softplc.core.image import ImageSizes
from softplc.hmi.server import ModbusSlave
from tests.fuzz import budget
from tests.fuzz.frames import broken_stream, mbap, random_pdu
from tests.fuzz.oracle import expected
from tests.hmi.helpers import (
    ImageSource,
    SlaveThread,
    connect,
    is_closed_by_peer,
    recv_adu,
    request,
    run_in_thread,
)

VALID_READ = bytes.fromhex("0400000001")  # %IW0


@pytest.fixture
def source() -> ImageSource:
    src = ImageSource(ImageSizes())
    rng = random.Random(5)
    img = src.image
    img.ix[:] = [rng.randrange(2) for _ in range(len(img.ix))]
    img.qx[:] = [rng.randrange(2) for _ in range(len(img.qx))]
    img.iw[:] = [rng.randrange(0x10000) for _ in range(len(img.iw))]
    img.qw[:] = [rng.randrange(0x10000) for _ in range(len(img.qw))]
    img.mw[:] = [rng.randrange(0x10000) for _ in range(len(img.mw))]
    src.publish()
    return src


def _slave(source: ImageSource, **options: float) -> SlaveThread:
    return run_in_thread(ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0,
                                     **options))  # type: ignore[arg-type]


@pytest.fixture
def slave(source: ImageSource) -> Iterator[SlaveThread]:
    with _slave(source, max_connections=8, idle_timeout_s=5.0) as handle:
        yield handle


def still_serves(port: int, source: ImageSource) -> None:
    """A fresh connection gets the exact answer to a well-formed read."""
    with connect(port) as sock:
        image = source.latest().image
        assert request(sock, VALID_READ, tid=4242) == bytes([4, 2]) + struct.pack(">H", image.iw[0])


def test_random_frames_get_the_answer_the_spec_prescribes(slave: SlaveThread,
                                                          source: ImageSource) -> None:
    rng = random.Random(budget.seed(20250101))
    batches, per_batch = budget.scaled(20), 50
    sent = dropped = exceptions = 0
    for _ in range(batches):
        snapshot = source.latest()
        frames, wanted = [], []
        for _ in range(per_batch):
            pdu, tid, unit = random_pdu(rng), rng.randrange(0x10000), rng.randrange(256)
            pid = 0 if rng.random() < 0.95 else rng.randrange(1, 0x10000)
            frames.append(mbap(pdu, tid, unit, pid))
            if pid == 0:  # any other protocol id is not Modbus: dropped without a reply
                wanted.append((tid, unit, pdu, expected(pdu, snapshot.image, snapshot.status)))
            else:
                dropped += 1
        with connect(slave.port) as sock:
            sock.sendall(b"".join(frames))
            for tid, unit, pdu, reply in wanted:
                r_tid, r_pid, r_unit, r_pdu = recv_adu(sock)
                assert (r_tid, r_pid, r_unit) == (tid, 0, unit)
                assert r_pdu == reply, f"request {pdu.hex()}: got {r_pdu.hex()}, want {reply.hex()}"
                exceptions += r_pdu[0] >= 0x80
        sent += len(frames)
        source.publish()  # the journaled writes reach the image, as a scan would do
        still_serves(slave.port, source)
    budget.record("modbus.random_frames", frames=sent, dropped_foreign_protocol=dropped,
                  exception_replies=exceptions, mismatches=0)


def _drain(sock: socket.socket, timeout_s: float) -> bytes:
    """Everything the server sends until it closes (or `timeout_s`)."""
    sock.settimeout(timeout_s)
    data = b""
    try:
        while chunk := sock.recv(65536):
            data += chunk
    except (TimeoutError, ConnectionResetError):
        pass
    return data


def _replies_are_well_formed(data: bytes) -> int:
    pos = count = 0
    while pos + 7 <= len(data):
        _tid, pid, length, _unit = struct.unpack_from(">HHHB", data, pos)
        pdu = data[pos + 7 : pos + 6 + length]
        assert pid == 0 and len(pdu) == length - 1 >= 1
        assert pdu[0] < 0x80 or pdu[1:] in (b"\1", b"\2", b"\3"), pdu.hex()
        pos, count = pos + 6 + length, count + 1
    assert pos == len(data), "a reply was cut short"
    return count


def test_broken_streams_close_only_their_own_connection(slave: SlaveThread,
                                                        source: ImageSource) -> None:
    rng = random.Random(budget.seed(77))
    streams, replies, closed = budget.scaled(60), 0, 0
    with connect(slave.port) as bystander:
        for i in range(streams):
            with connect(slave.port) as sock:
                sock.sendall(broken_stream(rng))
                sock.shutdown(socket.SHUT_WR)  # no more bytes: the server must not wait
                data = _drain(sock, 3.0)
                replies += _replies_are_well_formed(data)
                closed += 1
            if i % 10 == 0:
                assert request(bystander, VALID_READ, tid=i)[0] == 4
                still_serves(slave.port, source)
    deadline = time.monotonic() + 3
    while slave.slave.connection_count > 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert slave.slave.connection_count == 0
    budget.record("modbus.broken_streams", streams=streams, replies=replies,
                  connections_closed=closed)


def test_a_connection_flood_is_held_to_the_limit(source: ImageSource) -> None:
    limit, rounds = 8, budget.scaled(3)
    refused = served = 0
    with _slave(source, max_connections=limit, idle_timeout_s=5.0) as handle:
        for _ in range(rounds):
            flood = [connect(handle.port) for _ in range(5 * limit)]
            try:
                outcome = []
                for i, sock in enumerate(flood):
                    try:
                        outcome.append(request(sock, VALID_READ, tid=i)[0] == 4)
                    except (ConnectionError, TimeoutError):
                        outcome.append(False)
                # Held to the limit; idle connections make room for newer ones (the slave
                # evicts the one idle longest, docs/modbus.md; which ones survive depends on
                # the order the server accepted them): exactly `limit` are served.
                assert handle.slave.connection_count <= limit
                assert sum(outcome) == limit
                served += sum(outcome)
                refused += len(outcome) - sum(outcome)
            finally:
                for sock in flood:
                    sock.close()
            deadline = time.monotonic() + 3
            while handle.slave.connection_count > 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            still_serves(handle.port, source)
    budget.record("modbus.connection_flood", connections=rounds * 5 * limit, limit=limit,
                  served=served, refused=refused)


def test_stalled_clients_are_closed_and_others_served_meanwhile(source: ImageSource) -> None:
    idle_s = 0.5
    with _slave(source, idle_timeout_s=idle_s) as handle:
        half = connect(handle.port)
        half.sendall(mbap(VALID_READ, 1, 1)[:5])  # half a frame, then nothing
        trickle = connect(handle.port)
        frame = mbap(bytes.fromhex("1000000078f0") + bytes(240), 2, 1)
        started = time.monotonic()
        with connect(handle.port) as busy:
            trickle_closed = False
            for i in range(len(frame)):  # one byte every 50 ms: slower than the timeout
                if time.monotonic() - started > 3:
                    break
                try:
                    trickle.sendall(frame[i : i + 1])
                except OSError:
                    trickle_closed = True
                    break
                assert request(busy, VALID_READ, tid=i)[0] == 4
                time.sleep(0.05)
            assert is_closed_by_peer(half)
            assert trickle_closed or is_closed_by_peer(trickle)
            assert request(busy, VALID_READ, tid=999)[0] == 4
        elapsed = time.monotonic() - started
        half.close()
        trickle.close()
    budget.record("modbus.stalled_clients", idle_timeout_s=idle_s, closed_after_s=round(elapsed, 2))


def _rss_kib() -> int:
    with open("/proc/self/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def test_a_client_that_never_reads_holds_bounded_memory(source: ImageSource) -> None:
    n = budget.scaled(40_000)  # 12-byte requests, 259-byte replies: ~10 MB never read
    burst = b"".join(mbap(bytes.fromhex("030000007d"), i & 0xFFFF, 1) for i in range(n))
    with _slave(source, idle_timeout_s=10.0) as handle:
        rss_before = _rss_kib()
        hog = connect(handle.port, timeout_s=10)
        hog.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sender = threading.Thread(target=lambda: _send_quietly(hog, burst), daemon=True)
        sender.start()
        peak = 0
        with connect(handle.port) as other:
            for i in range(50):  # about 1 s in which the hog keeps sending and never reads
                peak = max(peak, handle.slave.buffered_bytes)
                assert request(other, VALID_READ, tid=i)[0] == 4
                time.sleep(0.02)
        rss_growth = _rss_kib() - rss_before
        hog.close()
        sender.join(10)
        deadline = time.monotonic() + 3
        while handle.slave.connection_count and time.monotonic() < deadline:
            time.sleep(0.01)
        assert handle.slave.connection_count == 0
        assert handle.slave.buffered_bytes == 0
        still_serves(handle.port, source)
    # one read segment of requests (256 KiB) + the transport's high-water mark (64 KiB) + 1
    assert peak <= 512 * 1024, peak
    budget.record("modbus.non_reader", requests_sent=n, peak_buffered_bytes=peak,
                  rss_growth_kib=rss_growth)


def _send_quietly(sock: socket.socket, data: bytes) -> None:
    with contextlib.suppress(OSError):  # closed while blocked: that is the point
        sock.sendall(data)
