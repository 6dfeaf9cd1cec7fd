"""The audit trail as server-sent events: `GET /api/v1/audit/events` (admin).

Owns: following the trail for one client (audit.py's Follower, in a thread, every POLL_S)
from where it asks (`Last-Event-ID: N`: the records after seq N the trail still keeps; else
from now), one `data:` line per record with `id:` = its seq, `event: overflow` with how many
records were skipped, heartbeats, and ending the stream (`event: end`) once the client's
credentials no longer give admin (decided again by security/decide.py at every poll: a
removed user, a revoked key, a changed password or a lowered role ends it within POLL_S).
Does not know: who writes the records (every process of the PLC and `softplc users` do:
that is why the file is followed, not this process's own writes), the program's events
(events.py), the route's role (roles.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Final

from aiohttp import web

from softplc.api.access import PRINCIPAL, Gate, Principal
from softplc.api.events import sse
from softplc.api.problems import ApiProblem
from softplc.security.audit import Follower
from softplc.security.roles import Act

POLL_S: Final = 0.25  # a record reaches the stream within about this
BATCH: Final = 1000  # records per poll at most (a replay): older ones are skipped and told


class AuditStreams:
    """The audit streams of one API server; `close` (on the app's shutdown) ends them."""

    def __init__(self, gate: Gate, heartbeat_s: float) -> None:
        self._gate = gate
        self._heartbeat_s = heartbeat_s
        self._closing = asyncio.Event()

    async def close(self, app: web.Application | None = None) -> None:
        self._closing.set()

    async def serve(self, request: web.Request) -> web.StreamResponse:
        """The stream of one client, until it goes away, loses admin or the server stops."""
        last_id = request.headers.get("Last-Event-ID")
        if last_id is not None and not last_id.strip().isdigit():
            raise ApiProblem(400, "Last-Event-ID must be an audit record's seq (a number)")
        after = None if last_id is None else int(last_id)
        # who the guard admitted, kept: decided again at every poll
        who = PRINCIPAL.get() or await self._gate.identify(request)
        follower = await asyncio.to_thread(Follower, self._gate.audit, after)
        response = web.StreamResponse(headers={
            "Content-Type": "text/event-stream", "Cache-Control": "no-cache",
            "X-Accel-Buffering": "no"})
        with contextlib.suppress(ConnectionResetError, asyncio.CancelledError):
            await response.prepare(request)
            await response.write(b"retry: 1000\n: connected\n\n")
            await self._follow(who, response, follower)
        return response

    async def _follow(self, who: Principal, response: web.StreamResponse,
                      follower: Follower) -> None:
        loop = asyncio.get_running_loop()
        said_s = loop.time()
        while not self._closing.is_set():
            decision = self._gate.decide(who, Act.AUDIT)  # acts at once (security/decide.py)
            if not decision.allowed:
                await response.write(_named("end", {"reason": decision.reason()}))
                return
            records, skipped = await asyncio.to_thread(follower.poll, BATCH)
            if skipped:
                await response.write(_named("overflow", {"dropped": skipped}))
            for record in records:
                await response.write(sse(record))
            now_s = loop.time()
            if records or skipped:
                said_s = now_s
            elif now_s - said_s >= self._heartbeat_s:
                await response.write(b": heartbeat\n\n")
                said_s = now_s
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._closing.wait(), POLL_S)


def _named(event: str, data: dict[str, object]) -> bytes:
    return f"event: {event}\ndata: {json.dumps(data)}\n\n".encode()
