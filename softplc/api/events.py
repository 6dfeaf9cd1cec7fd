"""Server-sent events (`GET /api/v1/events`) fed from the status board's event list.

Owns: one board poll shared by every listener while anyone listens, per-client bounded
queues (a slow client loses the oldest events and is told how many), replay after
Last-Event-ID, heartbeats, and noticing a restarted scan process (its seq starts again).
Does not know: how events are raised (the scan process puts them on the board), tokens.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any, Final

from aiohttp import web

from softplc.api.problems import ApiProblem

BOARD_POLL_S: Final = 0.05  # the scan process refreshes the board about every 50 ms
EVENT_QUEUE: Final = 1024  # per client; a slower client loses the oldest and is told


@dataclass(eq=False, slots=True)
class Subscriber:
    names: frozenset[str]
    after: int  # highest seq delivered or skipped
    queue: asyncio.Queue[dict[str, Any] | None] = field(
        default_factory=lambda: asyncio.Queue(EVENT_QUEUE))
    dropped: int = 0

    def offer(self, event: dict[str, Any]) -> None:
        seq = int(event["seq"])
        if seq <= self.after:
            return
        self.after = seq
        if self.names and event.get("name") not in self.names:
            return
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped += 1
        self.queue.put_nowait(event)


class EventHub:
    """Polls the board while anyone listens; hands each new event to every subscriber once."""

    def __init__(self, read_board: Callable[[], Awaitable[dict[str, Any]]]) -> None:
        self._read_board = read_board
        self._subscribers: set[Subscriber] = set()
        self._task: asyncio.Task[None] | None = None
        self._last = 0

    async def subscribe(self, names: frozenset[str], last_id: int | None) -> Subscriber:
        events = await self._events()
        newest = max((int(e["seq"]) for e in events), default=0)
        sub = Subscriber(names, newest if last_id is None else min(last_id, newest))
        for event in events:  # replay after Last-Event-ID; nothing otherwise
            sub.offer(event)
        self._subscribers.add(sub)
        if self._task is None or self._task.done():
            self._last = newest
            self._task = asyncio.create_task(self._run(), name="softplc-api-events")
        return sub

    def unsubscribe(self, sub: Subscriber) -> None:
        self._subscribers.discard(sub)

    async def close(self) -> None:
        for sub in self._subscribers:
            with contextlib.suppress(asyncio.QueueEmpty):
                if sub.queue.full():
                    sub.queue.get_nowait()
            sub.queue.put_nowait(None)
        self._subscribers.clear()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    async def serve(self, request: web.Request, heartbeat_s: float,
                    revoked: Callable[[], str | None] = lambda: None) -> web.StreamResponse:
        """The event stream of one client, until it goes away, the server stops or its
        identity may no longer read (`revoked`: why not, asked before everything it sends)."""
        names = frozenset(n.strip() for n in request.query.get("names", "").split(",")
                          if n.strip())
        last_id = request.headers.get("Last-Event-ID")
        if last_id is not None and not last_id.strip().isdigit():
            raise ApiProblem(400, "Last-Event-ID must be an event seq (a number)")
        sub = await self.subscribe(names, None if last_id is None else int(last_id))
        response = web.StreamResponse(headers={
            "Content-Type": "text/event-stream", "Cache-Control": "no-cache",
            "X-Accel-Buffering": "no"})
        try:
            await response.prepare(request)
            await response.write(b"retry: 1000\n: connected\n\n")
            await _stream(sub, response, heartbeat_s, revoked)
        except (ConnectionResetError, asyncio.CancelledError):
            pass  # the client went away
        finally:
            self.unsubscribe(sub)
        return response

    async def _events(self) -> list[dict[str, Any]]:
        try:
            events = (await self._read_board()).get("events") or []
        except (ApiProblem, ValueError):  # unavailable or torn: the next poll will do
            return []
        return [e for e in events if isinstance(e, dict) and isinstance(e.get("seq"), int)]

    async def _run(self) -> None:
        while self._subscribers:
            events = await self._events()
            newest = max((int(e["seq"]) for e in events), default=self._last)
            oldest = min((int(e["seq"]) for e in events), default=newest)
            if newest < self._last:  # the scan process restarted: its seq starts again
                for sub in self._subscribers:
                    sub.after = 0
            elif self._last and oldest > self._last + 1:  # more than the board holds
                for sub in self._subscribers:
                    sub.dropped += oldest - self._last - 1
            self._last = newest
            for event in events:
                for sub in self._subscribers:
                    sub.offer(event)
            await asyncio.sleep(BOARD_POLL_S)


async def _stream(sub: Subscriber, response: web.StreamResponse, heartbeat_s: float,
                  revoked: Callable[[], str | None]) -> None:
    reported = 0
    while True:
        try:
            event = await asyncio.wait_for(sub.queue.get(), heartbeat_s)
        except TimeoutError:
            event = {}
        if event is None:
            return  # the server stops
        if (reason := revoked()) is not None:  # a removed user, a changed password, ...
            await response.write(f"event: end\ndata: {json.dumps({'reason': reason})}\n\n"
                                 .encode())
            return
        if not event:
            await response.write(b": heartbeat\n\n")
            continue
        if sub.dropped != reported:
            reported = sub.dropped
            await response.write(f"event: overflow\ndata: {json.dumps({'dropped': reported})}"
                                 "\n\n".encode())
        await response.write(sse(event))


def sse(event: dict[str, Any]) -> bytes:
    """One event (or audit record: auditstream.py) with `id:` = its seq."""
    return f"id: {event['seq']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n".encode()
