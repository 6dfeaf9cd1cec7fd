"""Malformed OPC UA binary messages over raw sockets, a bounded number: the server answers or
drops them, and the scan does not notice (its count keeps rising, RUNNING, no fault)."""

from __future__ import annotations

import asyncio
import os
import random
import socket
import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import ua

from tests.opcua.conftest import Plc, patient_client, start_plc, stop_plc

CASES = 150 * int(os.environ.get("SOFTPLC_FUZZ_SCALE", "1"))


def _hello(url: bytes) -> bytes:
    body = struct.pack("<IIIII", 0, 65536, 65536, 0, 0) + struct.pack("<i", len(url)) + url
    return b"HELF" + struct.pack("<I", 8 + len(body)) + body


def _case(rng: random.Random, url: bytes) -> bytes:
    kind = rng.randrange(7)
    junk = rng.randbytes(rng.randrange(0, 200))
    if kind == 0:
        return junk  # noise
    if kind == 1:  # a header that promises more than it sends
        return b"HELF" + struct.pack("<I", rng.randrange(8, 1 << 31)) + junk
    if kind == 2:  # a length below the header's own size
        return b"MSGF" + struct.pack("<I", rng.randrange(0, 8)) + junk
    if kind == 3:  # a hello whose string length lies
        hello = bytearray(_hello(url))
        struct.pack_into("<i", hello, 28, rng.choice([-2, 1 << 30, len(url) + 50]))
        return bytes(hello)
    if kind == 4:  # a valid hello, then an OPN with garbage inside
        return _hello(url) + b"OPNF" + struct.pack("<I", 8 + len(junk)) + junk
    if kind == 5:  # a valid hello, then a MSG on a channel nobody opened
        return _hello(url) + b"MSGF" + struct.pack("<II", 16 + len(junk), 7) + b"\0" * 4 + junk
    flipped = bytearray(_hello(url))  # a hello with random bytes flipped
    for _ in range(rng.randrange(1, 6)):
        flipped[rng.randrange(len(flipped))] = rng.randrange(256)
    return bytes(flipped)


def _send(port: int, data: bytes) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=2) as s:
        s.settimeout(0.3)
        try:
            s.sendall(data)
            s.recv(4096)
        except OSError:
            pass  # dropped or silent: both fine, as long as the PLC goes on


async def _status(plc: Plc) -> tuple[int, str, int]:
    async with patient_client(plc.url) as client:
        ns = await client.get_namespace_index("urn:softplc")
        node = lambda name: client.get_node(ua.NodeId(f"PLC.Status.{name}", ns))  # noqa: E731
        return (int(await node("ScanCount").read_value()), await node("State").read_value(),
                int(await node("FaultCode").read_value()))


@pytest.fixture
def transport_plc(tmp_path: Path) -> Iterator[Plc]:
    """Timing is not what this test judges (tests must not depend on it): on a loaded
    2-core machine the fuzzing client and the comm process can starve the scan process for
    more than period x watchdog, a stall that says nothing about OPC UA. So stalls continue
    and the watchdog is wide; a fault of any other kind still fails the test."""
    plc = start_plc("programs/transport.yaml", tmp_path, "--on-stall", "continue",
                    "--watchdog", "100")
    try:
        yield plc
    finally:
        stop_plc(plc.proc)


def test_malformed_messages_do_not_disturb_the_scan(transport_plc: Plc) -> None:
    before = asyncio.run(_status(transport_plc))
    rng = random.Random(14)
    url = transport_plc.url.encode()
    for _ in range(CASES):
        _send(transport_plc.port, _case(rng, url))
    after = asyncio.run(_status(transport_plc))  # the server still answers a real client
    assert after[0] > before[0]
    assert after[1:] == ("RUNNING", 0)
    assert transport_plc.proc.poll() is None
