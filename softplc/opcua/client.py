"""The asyncua client every part of softplc uses to reach an OPC UA server (the `kind: opcua`
driver, the drilling cell's watcher; the tests' clients too).

Owns: one fix of asyncua 2.1's connect sequence. A server that refuses a connection closes
it at once (ours does past its per-peer cap, docs/opcua.md); when that close arrives between
the TCP connect and the Hello, asyncua's client has no transport left, sends nothing and
waits its whole request timeout for an Acknowledge that cannot come (measured: 6 of 16
refused connections waited 20 s). Here a connection already closed before the Hello is the
refusal it is: ConnectionError at once.
Does not know: what the caller does with the session.
"""

from __future__ import annotations

from asyncua import Client
from asyncua.client.ua_client import UASocketState


class RefusingAwareClient(Client):
    """asyncua's Client; a connection the server closed before the Hello fails at once."""

    async def send_hello(self) -> None:
        protocol = self.uaclient.protocol
        if protocol is None or protocol.state is UASocketState.CLOSED:
            raise ConnectionError(f"{self.server_url.geturl()} closed the connection before "
                                  "the Hello (refused: at a connection cap?)")
        await super().send_hello()
