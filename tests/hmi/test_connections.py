"""HMIs are never locked out: the connection rule over real sockets on loopback.

Idle and slowloris connections come from several loopback addresses (127.0.0.1..4, all
local on Linux), so both the per-peer limit and the total cap are exercised. Every count
and wait is bounded.
"""

from __future__ import annotations

import shutil
import socket
import struct
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager, suppress

import pytest
from pymodbus.client import ModbusTcpClient

from softplc.cli import build_parser
from softplc.hmi.admission import Limits
from softplc.hmi.server import ModbusSlave
from softplc.runtime.serve.comm import CommConfig, modbus_limits, modbus_slave
from tests.hmi.helpers import ImageSource, connect, is_closed_by_peer, request, run_in_thread
from tests.support import wait_until

IDLE_CONNECTIONS = 200
SLOWLORIS_CONNECTIONS = 20
PEERS = ("127.0.0.1", "127.0.0.2", "127.0.0.3", "127.0.0.4")
VALID_READ = bytes.fromhex("0400000001")
# An MBAP header announcing the longest ADU: a trickle of one byte per tick never completes.
SLOW_FRAME = struct.pack(">HHHB", 1, 0, 254, 1) + bytes([16]) + bytes(252)
COILS_0_7 = [True, False, False, True, False, False, False, False]  # the fixture's %QX0.0..7


def open_from(port: int, peer: str) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=3.0, source_address=(peer, 0))
    sock.settimeout(3.0)
    return sock


@contextmanager
def trickle(socks: list[socket.socket], tick_s: float = 0.05) -> Iterator[None]:
    """Slowloris: each socket sends one byte of SLOW_FRAME per tick until the block ends."""
    stop = threading.Event()

    def run() -> None:
        for i in range(len(SLOW_FRAME)):
            for sock in socks:
                with suppress(OSError):  # evicted: the slave closed it
                    sock.send(SLOW_FRAME[i : i + 1])
            if stop.wait(tick_s):
                return

    thread = threading.Thread(target=run, name="slowloris", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5.0)


@contextmanager
def crowded(slave: ModbusSlave, port: int) -> Iterator[None]:
    """200 idle connections spread over PEERS, then 20 slowloris ones from 127.0.0.1."""
    with ExitStack() as stack:
        for i in range(IDLE_CONNECTIONS):
            stack.enter_context(open_from(port, PEERS[i % len(PEERS)]))
        slow = [
            stack.enter_context(open_from(port, PEERS[0])) for _ in range(SLOWLORIS_CONNECTIONS)
        ]
        total = IDLE_CONNECTIONS + SLOWLORIS_CONNECTIONS
        assert wait_until(lambda: slave.connection_stats.admitted == total)
        with trickle(slow):
            time.sleep(0.2)  # a few bytes of each slow frame are in
            assert slave.connection_count == slave.max_connections
            yield


def crowded_slave(source: ImageSource) -> ModbusSlave:
    return ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0)


def test_pymodbus_client_reads_coils_at_the_first_try_among_220_idle_and_slow(
    source: ImageSource,
) -> None:
    slave = crowded_slave(source)
    with run_in_thread(slave) as handle, crowded(slave, handle.port):
        client = ModbusTcpClient("127.0.0.1", port=handle.port, timeout=3, retries=0)
        try:
            assert client.connect()
            for _ in range(3):  # and it keeps its slot while it polls
                assert client.read_coils(0, count=8, device_id=1).bits == COILS_0_7
        finally:
            client.close()
        stats = slave.connection_stats
        assert stats.refused == 0
        assert stats.evicted >= IDLE_CONNECTIONS + SLOWLORIS_CONNECTIONS + 1 - slave.max_connections
        assert slave.connection_count <= slave.max_connections


@pytest.mark.skipif(
    shutil.which("mbpoll") is None, reason="mbpoll is not installed (apt-get install -y mbpoll)"
)
def test_mbpoll_reads_coils_at_the_first_try_among_220_idle_and_slow(source: ImageSource) -> None:
    slave = crowded_slave(source)
    with run_in_thread(slave) as handle, crowded(slave, handle.port):
        cmd = [
            "mbpoll",
            "-m",
            "tcp",
            "-p",
            str(handle.port),
            "-a",
            "1",
            "-0",
            "-1",
            "-o",
            "2",
            "-t",
            "0",
            "-r",
            "0",
            "-c",
            "8",
            "127.0.0.1",
        ]
        result = subprocess.run(cmd, capture_output=True, text=True, timeout=15, check=False)
        assert result.returncode == 0, result.stderr
        assert "[0]: \t1" in result.stdout and "[3]: \t1" in result.stdout
        assert "[1]: \t0" in result.stdout


def test_a_client_polling_once_a_minute_yields_its_slot_when_others_need_it(
    source: ImageSource,
) -> None:
    # Scaled down: a 1 s live window stands for the default 10 s, a 1.2 s gap for a minute
    # (the window leaves a loaded machine time for the steps that need hmi still live).
    slave = ModbusSlave(
        source, source.sink, sizes=source.image.sizes, port=0, max_connections=2, live_window_s=1.0
    )
    with run_in_thread(slave) as handle, connect(handle.port) as rare, connect(handle.port) as hmi:
        assert request(rare, VALID_READ) == bytes.fromhex("04020000")
        time.sleep(1.2)  # rare's last traffic is older than the live window (a lower bound)
        assert request(hmi, VALID_READ) == bytes.fromhex("04020000")
        with connect(handle.port) as newcomer:
            assert request(newcomer, VALID_READ) == bytes.fromhex("04020000")
            assert is_closed_by_peer(rare)
            # Both slots now carry live traffic: a further connection is refused, not evicting.
            with connect(handle.port) as extra:
                assert is_closed_by_peer(extra)
            assert request(hmi, VALID_READ, tid=2) == bytes.fromhex("04020000")
            assert request(newcomer, VALID_READ, tid=2) == bytes.fromhex("04020000")
        stats = slave.connection_stats
        assert (stats.admitted, stats.evicted, stats.refused) == (3, 1, 1)


def test_per_peer_limit(source: ImageSource) -> None:
    slave = ModbusSlave(
        source,
        source.sink,
        sizes=source.image.sizes,
        port=0,
        max_connections=4,
        max_per_peer=2,
        live_window_s=30.0,
    )
    with run_in_thread(slave) as handle, ExitStack() as stack:
        busy = [stack.enter_context(open_from(handle.port, "127.0.0.2")) for _ in range(2)]
        for sock in busy:
            assert request(sock, VALID_READ) == bytes.fromhex("04020000")
        third = stack.enter_context(open_from(handle.port, "127.0.0.2"))
        assert is_closed_by_peer(third)  # its own two slots are live: refused
        other = stack.enter_context(open_from(handle.port, "127.0.0.3"))
        assert request(other, VALID_READ) == bytes.fromhex("04020000")
        idle = stack.enter_context(open_from(handle.port, "127.0.0.3"))
        assert wait_until(lambda: slave.connection_count == 4)
        # 127.0.0.3 is at its limit too; a new connection of it evicts its idle one.
        again = stack.enter_context(open_from(handle.port, "127.0.0.3"))
        assert request(again, VALID_READ) == bytes.fromhex("04020000")
        assert is_closed_by_peer(idle)
        for sock in (*busy, other):
            assert request(sock, VALID_READ, tid=5) == bytes.fromhex("04020000")


def test_run_flags_reach_the_slave_through_comm_config(source: ImageSource) -> None:
    args = build_parser().parse_args(
        ["run", "--modbus-max-connections", "3", "--modbus-max-per-peer", "2",
         "--modbus-idle-timeout", "400ms", "--modbus", "127.0.0.1:0"]
    )  # fmt: skip
    config = CommConfig(modbus=args.modbus, **modbus_limits(args))
    slave = modbus_slave(config, source, source.sink, dict)
    assert slave.limits == Limits(3, 2, 0.4, 0.4)
    with run_in_thread(slave) as handle, connect(handle.port) as idle:
        assert is_closed_by_peer(idle)  # after the 0.4 s idle timeout
        assert slave.connection_stats.idle_closed == 1
    assert modbus_limits(build_parser().parse_args(["run"])) == {
        "modbus_max_connections": 16,
        "modbus_max_per_peer": 8,
        "modbus_idle_timeout_s": 60.0,
    }


@pytest.mark.parametrize(
    "flag", ["--modbus-max-connections=0", "--modbus-max-per-peer=x", "--modbus-idle-timeout=0s"]
)
def test_bad_run_flags_are_refused(flag: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", flag])
    assert flag.split("=")[0] in capsys.readouterr().err
