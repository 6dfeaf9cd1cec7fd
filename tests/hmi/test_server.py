"""The slave over real sockets on 127.0.0.1 port 0: pymodbus clients and raw frames.

Every network wait is bounded by a socket timeout or a deadline; no test loops forever.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import random
import socket
import threading
import time

import pytest
from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient

from softplc.core.image import ImageSizes, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import ChannelFull, HmiWrite, Status
from softplc.hmi.map import STATUS_WORDS, status_registers
from softplc.hmi.server import ModbusSlave
from tests import support
from tests.hmi import cases
from tests.hmi.cases import Case
from tests.hmi.helpers import (
    ImageSource,
    SlaveThread,
    adu,
    connect,
    is_closed_by_peer,
    recv_adu,
    request,
    run_in_thread,
)

VALID_READ = bytes.fromhex("0400000001")  # %IW0, which the fixture sets to 0


wait_until = functools.partial(support.wait_until, timeout_s=3.0)  # a local server: 3 s


def client(slave: SlaveThread) -> ModbusTcpClient:
    c = ModbusTcpClient("127.0.0.1", port=slave.port, timeout=3, retries=0)
    assert c.connect()
    return c


# --- pymodbus clients -------------------------------------------------------------------


def test_pymodbus_client_reads_every_table(slave: SlaveThread, source: ImageSource) -> None:
    c = client(slave)
    try:
        for unit in (0, 1, 247):
            assert c.read_coils(0, count=8, device_id=unit).bits == [1, 0, 0, 1, 0, 0, 0, 0]
            assert c.read_coils(798, count=4, device_id=unit).bits[:4] == [0, 1, 0, 1]
            di = c.read_discrete_inputs(0, count=16, device_id=unit).bits
            assert [i for i, b in enumerate(di) if b] == [2, 15]
            assert c.read_input_registers(1020, count=4, device_id=unit).registers == [
                1020,
                1021,
                1022,
                1023,
            ]
            hr = c.read_holding_registers(1022, count=4, device_id=unit).registers
            assert hr == [2022, 2023, 5000, 5001]
        status = c.read_input_registers(1024, count=STATUS_WORDS).registers
        assert status == status_registers(source.latest().status)
    finally:
        c.close()


def test_status_block_over_the_network() -> None:
    status = Status(
        state=PlcState.RUNNING,
        scan_count=123_456,
        last_exec_us=250,
        max_exec_us=900,
        p99_lateness_us=40,
        overruns=2,
        program_hash="deadbeef00112233" + "0" * 48,
        period_us=10_000,
        forced=2,
    )
    src = ImageSource(ImageSizes(), status)
    with run_in_thread(ModbusSlave(src, src.sink, sizes=src.image.sizes, port=0)) as slave:
        c = client(slave)
        try:
            words = c.read_input_registers(1024, count=STATUS_WORDS).registers
        finally:
            c.close()
    hash_words = [0xDEAD, 0xBEEF, 0x0011, 0x2233]
    assert words == [2, 0, 1, 57920, 0, 250, 0, 900, 0, 40, 0, 2, 0, 10_000, *hash_words, 2, 0]


def test_pymodbus_client_writes_are_journaled_and_seen_after_publish(
    slave: SlaveThread, source: ImageSource
) -> None:
    c = client(slave)
    try:
        assert not c.write_coil(5, True).isError()
        assert not c.write_coils(801, [False, True]).isError()
        assert not c.write_register(1030, 77).isError()
        assert not c.write_registers(1023, [1, 2]).isError()
        rw = c.readwrite_registers(read_address=0, read_count=1, write_address=9, values=[9])
        assert rw.registers == [1000]
        assert source.writes == [
            HmiWrite(parse_address("%QX0.5"), (1,)),
            HmiWrite(parse_address("%MX0.1"), (0, 1)),
            HmiWrite(parse_address("%MW6"), (77,)),
            HmiWrite(parse_address("%QW1023"), (1,)),
            HmiWrite(parse_address("%MW0"), (2,)),
            HmiWrite(parse_address("%QW9"), (9,)),
        ]
        assert c.read_coils(5, count=1).bits[0] is False  # not before the next scan
        assert c.read_holding_registers(1030, count=1).registers == [5006]
        source.publish()
        assert c.read_coils(5, count=1).bits[0] is True
        assert c.read_coils(801, count=2).bits[:2] == [False, True]
        assert c.read_holding_registers(1023, count=2).registers == [1, 2]
        assert c.read_holding_registers(1030, count=1).registers == [77]
        assert c.read_holding_registers(9, count=1).registers == [9]
    finally:
        c.close()


def test_async_client_and_start_stop_on_one_loop(source: ImageSource) -> None:
    async def main() -> tuple[list[int], int]:
        slave = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0)
        async with slave:
            port = slave.bound_port
            c = AsyncModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
            assert await c.connect()
            regs = (await c.read_input_registers(0, count=3)).registers
            assert not (await c.write_register(2047, 3)).isError()
            assert slave.connection_count == 1
            c.close()
        return list(regs), port

    regs, port = asyncio.run(asyncio.wait_for(main(), 10))
    assert regs == [0, 1, 2]
    assert source.writes == [HmiWrite(parse_address("%MW1023"), (3,))]
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


# --- raw frames -------------------------------------------------------------------------


@pytest.mark.parametrize("index_case", list(enumerate(cases.ALL)), ids=lambda ic: ic[1].id)
def test_raw_frame(slave: SlaveThread, source: ImageSource, index_case: tuple[int, Case]) -> None:
    index, case = index_case
    tid, unit = 0x8000 + index * 97, (index * 37) % 256
    with connect(slave.port) as sock:
        assert request(sock, case.pdu, tid=tid, unit=unit) == case.reply
        assert tuple(source.writes) == case.writes
        assert request(sock, VALID_READ, tid=tid + 1, unit=unit) == bytes.fromhex("04020000")


def test_foreign_protocol_id_is_dropped_without_stalling(slave: SlaveThread) -> None:
    with connect(slave.port) as sock:
        sock.sendall(adu(VALID_READ, tid=1, pid=1))
        sock.settimeout(0.3)
        with pytest.raises(TimeoutError):
            sock.recv(1)
        sock.settimeout(3)
        assert request(sock, VALID_READ, tid=2) == bytes.fromhex("04020000")
        sock.sendall(adu(VALID_READ, tid=3, pid=0xFFFF) + adu(VALID_READ, tid=4))
        tid, _, _, pdu = recv_adu(sock)
        assert (tid, pdu) == (4, bytes.fromhex("04020000"))


@pytest.mark.parametrize("length", [0, 1, 255, 0xFFFF])
def test_impossible_mbap_length_closes_the_connection(slave: SlaveThread, length: int) -> None:
    with connect(slave.port) as sock:
        sock.sendall(b"\x00\x01\x00\x00" + length.to_bytes(2, "big") + b"\x01\x03\x00\x00")
        assert is_closed_by_peer(sock)
    with connect(slave.port) as sock:
        assert request(sock, VALID_READ) == bytes.fromhex("04020000")


def test_pipelined_requests_are_answered_in_order(slave: SlaveThread) -> None:
    reqs = [bytes.fromhex(h) for h in ("0400050001", "0300000000", "0100000008", "07")]
    with connect(slave.port) as sock:
        sock.sendall(b"".join(adu(p, tid=10 + i) for i, p in enumerate(reqs)))
        replies = [recv_adu(sock) for _ in reqs]
    assert [(r[0], r[3]) for r in replies] == [
        (10, bytes.fromhex("04020005")),
        (11, bytes.fromhex("8303")),
        (12, bytes.fromhex("010109")),
        (13, bytes.fromhex("8701")),
    ]


def test_a_burst_the_client_does_not_read_is_answered_completely(slave: SlaveThread) -> None:
    """20000 pipelined 125-register reads (5 MB of replies) sent before reading any: the
    slave stops reading while its send buffer is full, then answers every one in order."""
    n, reply_size = 20_000, 7 + 2 + 250
    burst = b"".join(adu(bytes.fromhex("030000007d"), tid=i) for i in range(n))
    with connect(slave.port, timeout_s=10) as sock:
        sender = threading.Thread(target=sock.sendall, args=(burst,), daemon=True)
        sender.start()
        time.sleep(0.5)
        received = bytearray()
        while len(received) < n * reply_size:
            chunk = sock.recv(1 << 20)
            assert chunk, f"EOF after {len(received)} bytes"
            received += chunk
        sender.join(10)
    assert len(received) == n * reply_size
    tids = [int.from_bytes(received[i : i + 2], "big") for i in range(0, len(received), reply_size)]
    assert tids == list(range(n))


def test_a_frame_sent_byte_by_byte_is_answered(slave: SlaveThread) -> None:
    with connect(slave.port) as sock:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for byte in adu(bytes.fromhex("0400070001"), tid=99):
            sock.sendall(bytes([byte]))
            time.sleep(0.002)
        assert recv_adu(sock) == (99, 0, 1, bytes.fromhex("04020007"))


def test_random_requests_get_one_reply_each_and_no_log_flood(
    slave: SlaveThread, caplog: pytest.LogCaptureFixture
) -> None:
    rng = random.Random(20240611)
    caplog.set_level(logging.DEBUG)
    caplog.clear()
    n = 300
    with connect(slave.port) as sock:
        for tid in range(n):
            fc = rng.choice([1, 2, 3, 4, 5, 6, 15, 16, 23, rng.randrange(256)])
            body = bytes(rng.randrange(256) for _ in range(rng.choice([0, 1, 4, 5, 9, 20])))
            unit = rng.randrange(256)
            sock.sendall(adu(bytes([fc]) + body, tid=tid, unit=unit))
            r_tid, r_pid, r_unit, r_pdu = recv_adu(sock)
            assert (r_tid, r_pid, r_unit) == (tid, 0, unit)
            assert r_pdu[0] == fc or (r_pdu[0] == fc | 0x80 and r_pdu[1:] in (b"\1", b"\2", b"\3"))
        assert request(sock, VALID_READ, tid=n) == bytes.fromhex("04020000")
    loud = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert loud == []
    from_pymodbus = [r for r in caplog.records if r.name.startswith("pymodbus")]
    # at most connect/disconnect lines, never one per frame (none at all when another test,
    # e.g. the remote-I/O driver, has raised the "pymodbus" logger's level first)
    assert len(from_pymodbus) < 20


def test_a_failing_sink_answers_04_and_the_slave_keeps_serving(source: ImageSource) -> None:
    def broken_sink(write: HmiWrite) -> None:
        raise RuntimeError("journal full")

    slave = ModbusSlave(source, broken_sink, sizes=source.image.sizes, port=0)
    with run_in_thread(slave) as handle, connect(handle.port) as sock:
        assert request(sock, bytes.fromhex("0600000001")) == bytes.fromhex("8604")
        assert request(sock, bytes.fromhex("0600000001")) == bytes.fromhex("8604")
        assert request(sock, VALID_READ) == bytes.fromhex("04020000")



def test_a_full_write_queue_answers_06_busy_in_one_log_line(
    source: ImageSource, caplog: pytest.LogCaptureFixture
) -> None:
    """The scan process does not drain HMI writes (overloaded, not running): the channel
    refuses at once. Modbus' answer is 06 (busy, retry), as HTTP's 503 and OPC UA's
    BadResourceUnavailable: not 04 with a traceback per write (issue 39 item 4)."""

    def full_queue(write: HmiWrite) -> None:
        raise ChannelFull(f"HMI write to {write.address} refused: queue full")

    slave = ModbusSlave(source, full_queue, sizes=source.image.sizes, port=0)
    with caplog.at_level(logging.INFO, logger="softplc.hmi"), run_in_thread(slave) as handle:
        c = client(handle)
        try:
            answers = [c.write_register(0, 1), c.write_coil(5, True),
                       c.write_registers(1023, [1, 2]), c.write_coils(0, [True, False])]
            answers += [c.write_register(7, n) for n in range(20)]
            assert [(a.isError(), getattr(a, "exception_code", None)) for a in answers] \
                == [(True, 6)] * len(answers)
            assert c.read_input_registers(0, count=1).registers == [0]  # reads go on
        finally:
            c.close()
    logged = [r for r in caplog.records if r.name.startswith("softplc.hmi")]
    assert len(logged) == 1, [r.getMessage() for r in logged]
    assert logged[0].exc_info is None and "06 (busy)" in logged[0].getMessage()

# --- connections ------------------------------------------------------------------------


def test_connection_limit(source: ImageSource) -> None:
    slave = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0, max_connections=2)
    with run_in_thread(slave) as handle:
        a, b = connect(handle.port), connect(handle.port)
        assert request(a, VALID_READ) == request(b, VALID_READ) == bytes.fromhex("04020000")
        extra = connect(handle.port)
        assert is_closed_by_peer(extra)
        extra.close()
        assert request(a, VALID_READ, tid=7) == bytes.fromhex("04020000")
        b.close()
        assert wait_until(lambda: slave.connection_count == 1)
        with connect(handle.port) as c:
            assert request(c, VALID_READ) == bytes.fromhex("04020000")
        a.close()


def test_idle_connections_are_closed(source: ImageSource) -> None:
    timeout_s = 1.0
    slave = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0,
                        idle_timeout_s=timeout_s)
    with run_in_thread(slave) as handle:
        # Before the connects: the slave's idle clock starts when it accepts, during them.
        started = time.monotonic()
        with connect(handle.port) as idle, connect(handle.port) as busy:
            last = time.monotonic()
            idle.settimeout(0.1)
            tid, longest_gap = 0, 0.0
            while True:  # busy polls every ~0.1 s until idle is closed: never idle for timeout_s
                assert request(busy, VALID_READ, tid=tid) == bytes.fromhex("04020000")
                now = time.monotonic()
                tid, longest_gap, last = tid + 1, max(longest_gap, now - last), now
                with contextlib.suppress(TimeoutError):
                    if is_closed_by_peer(idle):
                        break
                assert now - started < 10 * timeout_s, "idle was never closed"
            assert time.monotonic() - started >= timeout_s
            # The bound of this test's own polling, measured: busy was never silent for timeout_s.
            assert longest_gap < timeout_s, f"the machine stalled the test for {longest_gap:.2f} s"
            busy.settimeout(3 * timeout_s)
            assert request(busy, VALID_READ, tid=99) == bytes.fromhex("04020000")
            assert is_closed_by_peer(busy)
            assert wait_until(lambda: slave.connection_count == 0)


def test_stop_closes_client_connections_and_the_listener(source: ImageSource) -> None:
    handle = run_in_thread(ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0))
    port = handle.port
    sock = connect(port)
    assert request(sock, VALID_READ) == bytes.fromhex("04020000")
    handle.stop()
    assert is_closed_by_peer(sock)
    sock.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1).close()


def test_port_in_use_is_an_oserror(slave: SlaveThread, source: ImageSource) -> None:
    other = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=slave.port)
    with pytest.raises(OSError, match="cannot listen"):
        run_in_thread(other)
