"""Bounds of the HTTP API: connections, request classes, header timeout, body deadline, sizes.

Owns: `HttpLimits`, `Capacity` (the limits cut to the descriptors the process really has),
aiohttp's header limits and header/idle timeout, a site whose connections pass a gate (the
cap; eviction, idle unauthenticated connections first), the request classes and their
bounds, refusal counts for status (a summary log line per minute at most), the body deadline,
and a JSON body declared too big refused before any of it is read.
Does not know: routes, auth, the PLC, the channel (api/server.py classifies its routes).
Streams and ordinary requests are bounded below the cap, so `reserve` connections at least
are free or idle for priority requests (stop, status, the page): docs/api.md.

Why these mechanisms (aiohttp 3.14, web_protocol.py): a new connection gets aiohttp's
keep-alive timer at once, and when it fires while no complete request head has arrived
(the handler still waits for a message) the connection is closed. So `keepalive_timeout`
is both the header timeout of a new connection and the idle timeout between requests of a
kept-alive one; data trickling in does not extend it (slowloris). aiohttp has no body
deadline and no connection cap: those are the middleware and the gate here.
"""

from __future__ import annotations

import asyncio
import enum
import json
import logging
import os
import resource
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, replace
from typing import Any, Final

from aiohttp import web

from softplc.api.problems import MAX_JSON_BYTES
from softplc.core.errors import SoftplcError

log = logging.getLogger(__name__)

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
_REFUSAL_BODY: Final = json.dumps({"error": "too many connections: every connection is in a "
                                   "request; retry", "problems": []}).encode()
REFUSAL: Final = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                  b"Retry-After: 1\r\nConnection: close\r\nContent-Length: %d\r\n\r\n%s"
                  % (len(_REFUSAL_BODY), _REFUSAL_BODY))
SUMMARY_S: Final = 60.0  # refusals reach the log as one summary line per minute at most
MIN_CONNECTIONS: Final = 8  # even a process starved of descriptors serves stop and status


class Kind(enum.Enum):
    PRIORITY = "priority"  # stop, status, the page: never refused for capacity
    STREAM = "stream"  # an endless response (event streams): pools of their own
    ORDINARY = "ordinary"  # the rest: bounded together


# (method, path, has a body) -> (kind, pool); the pool names a stream's pool.
Classify = Callable[[str, str, bool], tuple[Kind, str]]


@dataclass(frozen=True, slots=True)
class HttpLimits:
    # A handful of operators, tools and pages; HMIs poll over Modbus, not here.
    max_connections: int = 128
    # Per stream pool (events, the page's live stream): in total, and from one address.
    max_streams: int = 16
    max_streams_per_peer: int = 8
    # Connections that streams and ordinary requests can never hold: stop, status, the page.
    reserve: int = 16
    # Of the descriptors free when the server starts (the HTTP process has its own table).
    fd_share: float = 0.25
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
        positive = ("max_connections", "max_streams", "max_streams_per_peer", "fd_share",
                    "header_timeout_s", "body_timeout_s", "max_line_size", "max_field_size",
                    "max_headers")
        bad = [f"{name} must be > 0, got {getattr(self, name)}" for name in positive
               if not getattr(self, name) > 0]
        bad += [f"{name} must be >= 0, got {getattr(self, name)}"
                for name in ("lingering_s", "reserve") if getattr(self, name) < 0]
        if bad:
            raise ValueError("; ".join(bad))

    def handler_args(self) -> dict[str, Any]:
        """aiohttp RequestHandler arguments, passed through `web.AppRunner(**...)`."""
        return {"keepalive_timeout": self.header_timeout_s, "lingering_time": self.lingering_s,
                **{k: getattr(self, k) for k in ("max_line_size", "max_field_size", "max_headers")}}


@dataclass(frozen=True, slots=True)
class Capacity:
    """The limits as enforced: the cap cut to the descriptors, the rest scaled with it."""

    connections: int
    streams: int  # per pool
    streams_per_peer: int
    ordinary: int  # ordinary requests in progress at once
    reserve: int
    fd_limit: int  # RLIMIT_NOFILE (soft) of this process

    @classmethod
    def of(cls, limits: HttpLimits, pools: int, fd_limit: int, fd_open: int) -> Capacity:
        budget = int(max(fd_limit - fd_open, 0) * limits.fd_share)
        cap = min(limits.max_connections, max(MIN_CONNECTIONS, budget))
        scale = cap / limits.max_connections
        reserve = min(max(int(limits.reserve * scale), 1 if limits.reserve else 0), cap // 4)
        streams = max(1, min(int(limits.max_streams * scale), (cap - reserve) // (2 * pools)))
        ordinary = max(1, cap - reserve - pools * streams)
        return cls(cap, streams, min(limits.max_streams_per_peer, streams), ordinary, reserve,
                   fd_limit)


def descriptors() -> tuple[int, int]:
    """(RLIMIT_NOFILE soft limit, descriptors open now) of this process."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    in_use = len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else 64
    return (soft if soft != resource.RLIM_INFINITY else 1 << 20), in_use


@dataclass(frozen=True, slots=True)
class ConnectionStats:
    admitted: int = 0
    evicted: int = 0  # closed while idle (no request running) to make room for a new one
    refused: int = 0  # answered 503: every connection was inside a request
    streams_refused: int = 0  # 503: the stream pool (or the peer's share of it) was full
    busy_refused: int = 0  # 503: too many ordinary requests in progress
    body_timeouts: int = 0  # 408: the body did not arrive within body_timeout_s
    too_large: int = 0  # 413 unread: a JSON body declared over MAX_JSON_BYTES (problems.py)


class Refused(SoftplcError):
    """A request over its class's bound: answered 503, Retry-After: 1."""


@dataclass(slots=True)
class _Entry:
    transport: asyncio.BaseTransport
    peer: str
    last_active_s: float  # connect, or the end of its last request
    busy: int = 0  # requests of this connection inside the app right now
    trusted: bool = False  # some request of it was answered other than 401/403


@dataclass(slots=True)
class Ticket:
    """One request inside the app: what it holds, given back by `leave`."""

    entry: _Entry | None
    peer: str
    kind: Kind
    pool: str


class _Gate:
    """The open connections, the requests in progress and the caps. Event loop only."""

    def __init__(self, capacity: Capacity) -> None:
        self.capacity = capacity
        self.stats = ConnectionStats()
        self._entries: dict[asyncio.BaseTransport, _Entry] = {}
        self._streams: Counter[tuple[str, str]] = Counter()  # (pool, peer) -> open streams
        self._ordinary = 0
        self._logged, self._logged_s = ConnectionStats(), -SUMMARY_S

    def admit(self, transport: asyncio.BaseTransport, peer: str, now_s: float) -> bool:
        if len(self._entries) >= self.capacity.connections and not self._evict_one():
            self.count("refused", now_s)
            return False
        self._entries[transport] = _Entry(transport, peer, now_s)
        self.count("admitted", now_s)
        return True

    def forget(self, transport: asyncio.BaseTransport) -> None:
        self._entries.pop(transport, None)

    def enter(self, transport: asyncio.BaseTransport | None, peer: str, kind: Kind, pool: str,
              now_s: float) -> Ticket:
        # No entry: evicted while its request head was already parsed. It still counts.
        entry = self._entries.get(transport) if transport is not None else None
        if kind is Kind.STREAM:
            self._check_stream(pool, peer, now_s)
            self._streams[(pool, peer)] += 1
        elif kind is Kind.ORDINARY:
            if self._ordinary >= self.capacity.ordinary:
                self.count("busy_refused", now_s)
                raise Refused(f"server busy: {self._ordinary} requests in progress (the "
                              "limit); retry, or use stop and status, which are always served")
            self._ordinary += 1
        if entry is not None:
            entry.busy += 1
        return Ticket(entry, peer, kind, pool)

    def _check_stream(self, pool: str, peer: str, now_s: float) -> None:
        total = sum(n for (p, _), n in self._streams.items() if p == pool)
        if total >= self.capacity.streams:
            self.count("streams_refused", now_s)
            raise Refused(f"too many {pool} streams: {total} open (the limit); close one")
        if self._streams[(pool, peer)] >= self.capacity.streams_per_peer:
            self.count("streams_refused", now_s)
            raise Refused(f"too many {pool} streams from {peer}: "
                          f"{self.capacity.streams_per_peer} open (the limit per address)")

    def leave(self, ticket: Ticket, answered: int, now_s: float) -> None:
        if ticket.kind is Kind.STREAM:
            key = (ticket.pool, ticket.peer)
            self._streams[key] -= 1
            if self._streams[key] <= 0:
                del self._streams[key]
        elif ticket.kind is Kind.ORDINARY:
            self._ordinary -= 1
        if ticket.entry is not None:
            ticket.entry.busy -= 1
            ticket.entry.last_active_s = now_s
            ticket.entry.trusted |= answered not in (401, 403)

    def _evict_one(self) -> bool:
        idle = [entry for entry in self._entries.values() if entry.busy == 0]
        if not idle:
            return False
        per_peer = Counter(entry.peer for entry in self._entries.values())
        victim = min(idle, key=lambda e: (e.trusted, -per_peer[e.peer], e.last_active_s))
        del self._entries[victim.transport]
        victim.transport.close()  # flushes a reply still being written, then closes
        self.count("evicted", 0.0)
        return True

    def count(self, outcome: str, now_s: float) -> None:
        self.stats = replace(self.stats, **{outcome: getattr(self.stats, outcome) + 1})
        if outcome in ("refused", "streams_refused", "busy_refused"):
            self._summarise(now_s)

    def _summarise(self, now_s: float) -> None:
        """One log line for the first refusal, then at most one per SUMMARY_S: a flood of
        refused clients must not become a flood of log lines."""
        if now_s - self._logged_s < SUMMARY_S:
            return
        then, now = asdict(self._logged), asdict(self.stats)
        counts = ", ".join(f"{key} {now[key] - then[key]}" for key in now if key != "admitted")
        log.warning("HTTP door, since the last summary: %s (connections %d of %d)", counts,
                    len(self._entries), self.capacity.connections)
        self._logged, self._logged_s = self.stats, now_s

    def report(self) -> dict[str, Any]:
        return {**asdict(self.stats), "connections": len(self._entries),
                "ordinary_in_progress": self._ordinary, "streams": dict(sum(
                    (Counter({pool: n}) for (pool, _), n in self._streams.items()), Counter())),
                "capacity": asdict(self.capacity)}


class _GatedProtocol(asyncio.Protocol):
    """Stands in front of aiohttp's RequestHandler: a refused connection never reaches it."""

    def __init__(self, gate: _Gate, make_inner: Callable[[], asyncio.Protocol]) -> None:
        self._gate, self._make_inner = gate, make_inner
        self._inner: asyncio.Protocol | None = None
        self._transport: asyncio.BaseTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        peer = transport.get_extra_info("peername")
        peer = str(peer[0]) if isinstance(peer, tuple) and peer else "?"
        if not self._gate.admit(transport, peer, asyncio.get_running_loop().time()):
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
        # asyncio accepts up to `backlog` sockets per loop turn before any is admitted or
        # evicted: that burst counts against the descriptors too.
        backlog = min(self._backlog, gate.capacity.connections)
        self._server = await asyncio.get_running_loop().create_server(
            lambda: _GatedProtocol(gate, server), self._host, self._port,
            backlog=backlog, reuse_address=True,
        )  # fmt: skip


class HttpBounds:
    """One server's bounds: `runner(app)` then `site(runner, host, port)` instead of
    `web.AppRunner(app)` and `web.TCPSite(runner, host, port)`. Without `classify` every
    request is bounded by the connection cap only; `pools` names the stream pools."""

    def __init__(self, limits: HttpLimits | None = None, classify: Classify | None = None,
                 pools: int = 1) -> None:
        self.limits = limits or HttpLimits()
        self._classify = classify or (lambda method, path, body: (Kind.PRIORITY, ""))
        self._gate = _Gate(Capacity.of(self.limits, pools, *descriptors()))

    @property
    def stats(self) -> ConnectionStats:
        return self._gate.stats

    @property
    def capacity(self) -> Capacity:
        return self._gate.capacity

    @property
    def connection_count(self) -> int:
        return int(self._gate.report()["connections"])

    def report(self) -> dict[str, Any]:
        """Counts since start, connections and streams open, the capacity: for status."""
        return self._gate.report()

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
        loop = asyncio.get_running_loop()
        kind, pool = self._classify(request.method, request.path, request.can_read_body)
        try:
            ticket = self._gate.enter(request.transport, request.remote or "?", kind, pool,
                                      loop.time())
        except Refused as exc:
            return web.json_response({"error": str(exc), "problems": []}, status=503,
                                     headers={"Retry-After": "1"})
        response: web.StreamResponse | None = None
        try:
            response = await handler(request)
            return response
        finally:
            self._gate.leave(ticket, 500 if response is None else response.status, loop.time())

    @web.middleware
    async def _body_deadline(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        # A JSON value write declared too big is never read; aiohttp drops it (lingering_s).
        declared = request.content_length or 0
        if declared > MAX_JSON_BYTES and request.content_type.endswith("json"):
            self._gate.count("too_large", asyncio.get_running_loop().time())
            return web.json_response({"error": f"JSON body of {declared} bytes: at most "
                                      f"{MAX_JSON_BYTES}", "problems": []}, status=413)
        if request.can_read_body:
            try:
                async with asyncio.timeout(self.limits.body_timeout_s):
                    await request.read()  # cached: the handler's read()/text()/json() reuse it
            except TimeoutError:
                self._gate.count("body_timeouts", asyncio.get_running_loop().time())
                raise web.HTTPRequestTimeout(
                    text=f"the request body did not arrive within {self.limits.body_timeout_s:g} s"
                ) from None
        return await handler(request)
