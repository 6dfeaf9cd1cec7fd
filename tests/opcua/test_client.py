"""softplc's asyncua client against a server that refuses a connection by closing it (as
ours does past its per-peer cap): the refusal is an error at once, never a wait for an
Acknowledge that cannot come."""

from __future__ import annotations

import asyncio
import socket
import threading

import pytest
from asyncua.client.ua_client import UASocketState

from softplc.opcua.client import RefusingAwareClient


@pytest.fixture
def closing_server() -> tuple[int, threading.Event]:
    """A loopback listener that closes every connection it accepts (bounded: 5 accepts)."""
    listener = socket.create_server(("127.0.0.1", 0))
    done = threading.Event()

    def serve() -> None:
        with listener:
            listener.settimeout(10)
            for _ in range(5):
                try:
                    conn, _ = listener.accept()
                except OSError:
                    break
                conn.close()
        done.set()

    threading.Thread(target=serve, daemon=True).start()
    return listener.getsockname()[1], done


def test_a_connection_closed_before_the_hello_is_refused_at_once(
        closing_server: tuple[int, threading.Event]) -> None:
    port, _ = closing_server

    async def scenario() -> None:
        # The request timeout is what asyncua's own client waits here: a TimeoutError after
        # it, where the refusal should be a ConnectionError.
        client = RefusingAwareClient(f"opc.tcp://127.0.0.1:{port}", timeout=2)
        await client.connect_socket()
        protocol = client.uaclient.protocol
        assert protocol is not None
        for _ in range(1000):  # the server's close reaches the client's protocol
            if protocol.state is UASocketState.CLOSED:
                break
            await asyncio.sleep(0.005)
        assert protocol.state is UASocketState.CLOSED
        with pytest.raises(ConnectionError, match="closed the connection before the Hello"):
            await client.send_hello()

    asyncio.run(scenario())


def test_connect_to_a_refusing_server_fails_with_a_connection_error(
        closing_server: tuple[int, threading.Event]) -> None:
    port, _ = closing_server

    async def scenario() -> None:
        client = RefusingAwareClient(f"opc.tcp://127.0.0.1:{port}", timeout=2)
        with pytest.raises(ConnectionError):
            await client.connect()

    for _ in range(3):  # either side of the race: closed before the Hello or after it
        asyncio.run(scenario())
