"""Bounds of the HTTP API: connection cap, header timeout, body read deadline, size limits.

Owns: `HttpLimits` (the numbers), the aiohttp `AppRunner` arguments that enforce header size
limits and the header/idle timeout, a listening site whose connections pass a gate (cap:
evict the connection idle longest, refuse with 503 only when every connection is inside a
request), and a middleware that gives a request body one deadline.
Does not know: routes, auth, the PLC, the channel (api/server.py).

Why these mechanisms (aiohttp 3.14, web_protocol.py): a new connection gets aiohttp's
keep-alive timer at once, and when it fires while no complete request head has arrived
(the handler still waits for a message) the connection is closed. So `keepalive_timeout`
is both the header timeout of a new connection and the idle timeout between requests of a
kept-alive one; data trickling in does not extend it (slowloris). aiohttp has no body
deadline and no connection cap: those are the middleware and the gate here.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, replace
from typing import Any, Final

from aiohttp import web

log = logging.getLogger(__name__)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
_REFUSAL_BODY: Final = json.dumps(
    {"error": "too many connections: every connection is in a request; retry", "problems": []}
).encode()
REFUSAL: Final = (
    b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
    b"Retry-After: 1\r\nConnection: close\r\n"
    + f"Content-Length: {len(_REFUSAL_BODY)}\r\n\r\n".encode()
    + _REFUSAL_BODY
)


@dataclass(frozen=True, slots=True)
class HttpLimits:
    # A handful of operators, tools and pages; HMIs poll over Modbus, not here.
    max_connections: int = 128
    # A new connection must deliver a complete request head within this, and a kept-alive
    # connection is closed after this long without a request.
    header_timeout_s: float = 10.0
    # Whole body, from the handler's start: 1 MiB (the body limit) at >= 35 KB/s.
    body_timeout_s: float = 30.0
    # After a refused or timed-out request, unread body is read and dropped this long at most.
    lingering_s: float = 1.0
    max_line_size: int = 8190
    max_field_size: int = 8190
    # With the field size: at most ~256 KiB of header buffer per connection.
    max_headers: int = 32

    def __post_init__(self) -> None:
        bad = [
            f"{name} must be > 0, got {value}"
            for name, value in (
                ("max_connections", self.max_connections),
                ("header_timeout_s", self.header_timeout_s),
                ("body_timeout_s", self.body_timeout_s),
                ("max_line_size", self.max_line_size),
                ("max_field_size", self.max_field_size),
                ("max_headers", self.max_headers),
            )
            if not value > 0
        ]
        if self.lingering_s < 0:
            bad.append(f"lingering_s must be >= 0, got {self.lingering_s}")
        if bad:
            raise ValueError("; ".join(bad))

    def handler_args(self) -> dict[str, Any]:
        """aiohttp RequestHandler arguments, passed through `web.AppRunner(**...)`."""
        return {
            "keepalive_timeout": self.header_timeout_s,
            "lingering_time": self.lingering_s,
            "max_line_size": self.max_line_size,
            "max_field_size": self.max_field_size,
            "max_headers": self.max_headers,
        }


@dataclass(frozen=True, slots=True)
class ConnectionStats:
    admitted: int = 0
    evicted: int = 0  # closed while idle (no request running) to make room for a new one
    refused: int = 0  # answered 503: every connection was inside a request
    body_timeouts: int = 0  # 408: the body did not arrive within body_timeout_s


@dataclass(slots=True)
class _Entry:
    transport: asyncio.BaseTransport
    last_active_s: float  # connect, or the end of its last request
    busy: int = 0  # requests of this connection inside the app right now


class _Gate:
    """The open connections and the cap. Runs on the server's event loop only."""

    def __init__(self, limits: HttpLimits) -> None:
        self.limits = limits
        self.stats = ConnectionStats()
        self._entries: dict[asyncio.BaseTransport, _Entry] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def admit(self, transport: asyncio.BaseTransport, now_s: float) -> bool:
        if len(self._entries) >= self.limits.max_connections and not self._evict_one():
            self.count("refused")
            return False
        self._entries[transport] = _Entry(transport, now_s)
        self.count("admitted")
        return True

    def forget(self, transport: asyncio.BaseTransport) -> None:
        self._entries.pop(transport, None)

    def enter(self, transport: asyncio.BaseTransport | None) -> _Entry | None:
        entry = self._entries.get(transport) if transport is not None else None
        if entry is not None:
            entry.busy += 1
        return entry

    def leave(self, entry: _Entry | None, now_s: float) -> None:
        if entry is not None:
            entry.busy -= 1
            entry.last_active_s = now_s

    def _evict_one(self) -> bool:
        idle = [entry for entry in self._entries.values() if entry.busy == 0]
        if not idle:
            return False
        victim = min(idle, key=lambda entry: entry.last_active_s)
        del self._entries[victim.transport]
        victim.transport.close()  # flushes a reply still being written, then closes
        self.count("evicted")
        return True

    def count(self, outcome: str) -> None:
        self.stats = replace(self.stats, **{outcome: getattr(self.stats, outcome) + 1})


class _GatedProtocol(asyncio.Protocol):
    """Stands in front of aiohttp's RequestHandler: a refused connection never reaches it."""

    def __init__(self, gate: _Gate, make_inner: Callable[[], asyncio.Protocol]) -> None:
        self._gate = gate
        self._make_inner = make_inner
        self._inner: asyncio.Protocol | None = None
        self._transport: asyncio.BaseTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        loop = asyncio.get_running_loop()
        if not self._gate.admit(transport, loop.time()):
            log.debug("HTTP connection refused: %d connections, all in a request", len(self._gate))
            if isinstance(transport, asyncio.WriteTransport):
                transport.write(REFUSAL)
            transport.close()
            return
        self._transport = transport
        self._inner = self._make_inner()
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if self._inner is not None:
            self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return None if self._inner is None else self._inner.eof_received()

    def pause_writing(self) -> None:
        if self._inner is not None:
            self._inner.pause_writing()

    def resume_writing(self) -> None:
        if self._inner is not None:
            self._inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._transport is not None:
            self._gate.forget(self._transport)
        if self._inner is not None:
            self._inner.connection_lost(exc)


class _BoundedSite(web.BaseSite):
    """`web.TCPSite` whose connections pass the gate first."""

    __slots__ = ("_gate", "_host", "_port")

    def __init__(self, runner: web.BaseRunner, host: str, port: int, gate: _Gate) -> None:
        super().__init__(runner)
        self._host, self._port, self._gate = host, port, gate

    @property
    def name(self) -> str:
        return f"http://{self._host}:{self._port}"

    async def start(self) -> None:
        await super().start()
        server = self._runner.server
        assert server is not None, "the runner is set up before its site starts"
        gate = self._gate
        self._server = await asyncio.get_running_loop().create_server(
            lambda: _GatedProtocol(gate, server), self._host, self._port,
            backlog=self._backlog, reuse_address=True,
        )  # fmt: skip


class HttpBounds:
    """One server's bounds: `runner(app)` then `site(runner, host, port)` instead of
    `web.AppRunner(app)` and `web.TCPSite(runner, host, port)`."""

    def __init__(self, limits: HttpLimits | None = None) -> None:
        self.limits = limits or HttpLimits()
        self._gate = _Gate(self.limits)

    @property
    def stats(self) -> ConnectionStats:
        return self._gate.stats

    @property
    def connection_count(self) -> int:
        return len(self._gate)

    def runner(self, app: web.Application, **kwargs: Any) -> web.AppRunner:
        # Outermost: a request counts as busy for the whole of its handling. Innermost: the
        # body deadline, after the app's own checks (auth) have refused what they refuse.
        app.middlewares.insert(0, self._track)
        app.middlewares.append(self._body_deadline)
        return web.AppRunner(app, **self.limits.handler_args(), **kwargs)

    def site(self, runner: web.BaseRunner, host: str, port: int) -> web.BaseSite:
        return _BoundedSite(runner, host, port, self._gate)

    @web.middleware
    async def _track(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        entry = self._gate.enter(request.transport)
        try:
            return await handler(request)
        finally:
            self._gate.leave(entry, asyncio.get_running_loop().time())

    @web.middleware
    async def _body_deadline(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        if request.can_read_body:
            try:
                async with asyncio.timeout(self.limits.body_timeout_s):
                    await request.read()  # cached: the handler's read()/text()/json() reuse it
            except TimeoutError:
                self._gate.count("body_timeouts")
                raise web.HTTPRequestTimeout(
                    text=f"the request body did not arrive within {self.limits.body_timeout_s:g} s"
                ) from None
        return await handler(request)
