"""TLS on the API's bounded connections: the connection gate (api/limits.py) admits, counts
and evicts a connection before its handshake, then TLS runs between it and aiohttp.

Owns: `TlsRunner`, an aiohttp runner whose protocol factory wraps each request handler in
asyncio's TLS protocol (what `create_server(ssl=...)` would put in the same place, but inside
the gate: a client that stalls in its handshake holds an idle, evictable slot, and is closed
after HANDSHAKE_TIMEOUT_S).
Does not know: certificates (tls.py), routes, limits.
"""

from __future__ import annotations

import asyncio
import ssl
from asyncio.sslproto import SSLProtocol
from collections.abc import Callable
from typing import Any, Final

from aiohttp import web

HANDSHAKE_TIMEOUT_S: Final = 10  # the header timeout's order: a handshake is a few round trips


class TlsRunner(web.AppRunner):
    """`web.AppRunner` speaking TLS with `context`; built with `around(runner, context)`
    from the runner api/limits.py made, with the same app and arguments."""

    def __init__(self, app: web.Application, context: ssl.SSLContext, **kwargs: Any) -> None:
        super().__init__(app, **kwargs)
        self._context = context

    @classmethod
    def around(cls, runner: web.AppRunner, context: ssl.SSLContext) -> TlsRunner:
        return cls(runner.app, context, **runner._kwargs)  # not set up yet: nothing to move

    @property
    def server(self) -> Any:  # the sites call it for each connection, as they do a Server
        inner = super().server
        if inner is None:
            return None
        context = self._context
        return lambda: _TlsConnection(inner, context)


class _TlsConnection(asyncio.Protocol):
    """A plain protocol (what the gate forwards to) in front of asyncio's buffered TLS
    protocol, which decrypts for aiohttp's handler and encrypts its answers."""

    def __init__(self, make_handler: Callable[[], asyncio.BaseProtocol],
                 context: ssl.SSLContext) -> None:
        loop = asyncio.get_running_loop()
        handshake = loop.create_future()  # a client's failed handshake is no error of ours
        handshake.add_done_callback(lambda done: done.cancelled() or done.exception())
        self._tls = SSLProtocol(loop, make_handler(), context, handshake,
                                server_side=True, ssl_handshake_timeout=HANDSHAKE_TIMEOUT_S)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._tls.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            buffer = self._tls.get_buffer(len(view))
            size = min(len(buffer), len(view))
            buffer[:size] = view[:size]
            self._tls.buffer_updated(size)
            view = view[size:]

    def eof_received(self) -> None:
        self._tls.eof_received()  # it closes the TLS session: never half-open

    def pause_writing(self) -> None:
        self._tls.pause_writing()

    def resume_writing(self) -> None:
        self._tls.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        self._tls.connection_lost(exc)
