"""The operator's page and forcing over HTTP, registered on the API's aiohttp app.

Owns: `/` (the page) and `/static/...` (its vendored libraries, softplc/api/static/), the
net's structure (`GET /api/v1/net`), the decimated live stream for pages (`GET
/api/v1/live`, server-sent events, at most LIVE_HZ frames a second however fast the PLC
scans, one board poll shared by every page), and forcing (`GET /api/v1/forces`, `PUT` and
`DELETE /api/v1/forces/{name}`, `DELETE /api/v1/forces`).
Does not know: the scan (forces travel as FORCE/UNFORCE commands through the server's
channel and are checked by core/forcing.py), tokens and Host rules (server.py's guard; the
page and its static files carry no data and are the only routes served without a token).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from softplc.api.openapi import API_PREFIX
from softplc.api.pagedoc import LIVE_HZ
from softplc.api.problems import json_body
from softplc.api.service import ApiService
from softplc.api.symbols import value_of_entry, write_raw
from softplc.core.lifecycle import Command
from softplc.core.snapshot import CommandReply, SnapshotUnavailable

STATIC: Final = Path(__file__).with_name("static")
PUBLIC_PREFIXES: Final = ("/static/",)
PUBLIC_PATHS: Final = frozenset({"/", "/index.html"})
# The page loads only its own files and talks only to its own origin.
CSP: Final = ("default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; "
              "connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'; "
              "form-action 'none'")


def is_public(method: str, path: str) -> bool:
    """The page and its static files: no data in them, served without a token so that the
    page can ask for one. Host and Origin checks still apply."""
    return method in ("GET", "HEAD") and (path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIXES))


def register(app: web.Application, api: ApiService) -> None:
    """Add the page's routes to `app` (server.py's build_app calls this once)."""
    routes = _Routes(api)
    p = API_PREFIX
    app.router.add_get("/", routes.page)
    app.router.add_get("/index.html", routes.page)
    app.router.add_static("/static/", STATIC, follow_symlinks=False)
    app.router.add_get(f"{p}/net", routes.net)
    app.router.add_get(f"{p}/live", routes.live)
    app.router.add_get(f"{p}/forces", routes.forces)
    app.router.add_put(f"{p}/forces/{{name}}", routes.force)
    app.router.add_delete(f"{p}/forces/{{name}}", routes.unforce)
    app.router.add_delete(f"{p}/forces", routes.unforce)
    app.on_shutdown.append(routes.close)


@dataclass(eq=False, slots=True)
class _Viewer:
    """One page's stream: only the newest frame waits (a slow page skips frames, never
    queues them); events of skipped frames are carried into the next one."""

    ready: asyncio.Event = field(default_factory=asyncio.Event)
    frame: dict[str, Any] | None = None
    closed: bool = False

    def offer(self, frame: dict[str, Any]) -> None:
        if self.frame is not None:
            frame = {**frame, "events": self.frame["events"] + frame["events"]}
        self.frame = frame
        self.ready.set()


class _LiveHub:
    """One poll of board and snapshot for all pages while any page listens."""

    def __init__(self, api: ApiService) -> None:
        self._api = api
        self._viewers: set[_Viewer] = set()
        self._task: asyncio.Task[None] | None = None
        self._last_event = 0
        self._last_key: tuple[Any, ...] = ()

    def join(self) -> _Viewer:
        viewer = _Viewer()
        self._viewers.add(viewer)
        self._last_key = ()  # a new page gets a frame at once
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._run(), name="softplc-web-live")
        return viewer

    def leave(self, viewer: _Viewer) -> None:
        self._viewers.discard(viewer)

    async def close(self) -> None:
        for viewer in self._viewers:
            viewer.closed = True
            viewer.ready.set()
        self._viewers.clear()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    async def _run(self) -> None:
        interval = 1.0 / LIVE_HZ
        while self._viewers:
            started = time.monotonic()
            with contextlib.suppress(web.HTTPException, ValueError, TimeoutError):
                frame = await self._frame()
                if frame is not None:
                    for viewer in self._viewers:
                        viewer.offer(frame)
            await asyncio.sleep(max(interval - (time.monotonic() - started), 0.005))

    async def _frame(self) -> dict[str, Any] | None:
        document = await self._api.board_document()
        status = None
        with contextlib.suppress(SnapshotUnavailable):
            status = self._api.snapshots.latest().status
        key = (document.get("scan_count"), None if status is None else
               (status.scan_count, status.state, status.forced))
        if key == self._last_key:
            return None  # nothing new: no frame (a stopped PLC costs nothing)
        self._last_key = key
        return live_frame(document, status, self._api.image()[1], self._new_events(document))

    def _new_events(self, document: dict[str, Any]) -> list[dict[str, Any]]:
        events = [e for e in document.get("events") or []
                  if isinstance(e, dict) and isinstance(e.get("seq"), int)]
        newest = max((e["seq"] for e in events), default=0)
        if newest < self._last_event:  # the scan process restarted
            self._last_event = 0
        fresh = [e for e in events if e["seq"] > self._last_event][-64:]
        self._last_event = max(newest, self._last_event)
        return fresh


def live_frame(document: dict[str, Any], status: Any, image: Any,
               events: list[dict[str, Any]]) -> dict[str, Any]:
    """What a page needs each frame: state, marking, live net, values, forces, timing."""
    symbols = document.get("symbols") or {}
    values = {name: value_of_entry(entry, image) if isinstance(entry, dict) else 0
              for name, entry in symbols.items()}  # typed: core/present.py
    timing = document.get("timing") or {}
    frame: dict[str, Any] = {
        "wall_ms": int(time.time() * 1000),
        "state": document.get("state"), "scan_count": document.get("scan_count", 0),
        "board_scan_count": document.get("scan_count", 0),  # the scan of marking and net_live
        "program": document.get("program"), "program_hash": document.get("program_hash"),
        "start_mode": document.get("start_mode"), "start_reason": document.get("start_reason"),
        "boot_policy": document.get("boot_policy"),
        "fault_reason": document.get("fault_reason", ""), "period_us": document.get("period_us"),
        "marking": document.get("marking") or {}, "net_live": document.get("net_live") or {},
        "forced": document.get("forced") or {}, "values": values, "events": events,
        "waiting_for_devices": document.get("waiting_for_devices") or [],  # issue 26
        "waiting": document.get("waiting") or [],  # why nothing moves (core/waiting.py)
        "paused": document.get("paused"),  # at a breakpoint (docs/debug.md)
        "timing": {k: timing.get(k) for k in (
            "exec_median_us", "exec_p99_us", "exec_max_us", "lateness_median_us",
            "lateness_p99_us", "lateness_max_us", "overruns")},
    }
    if status is not None and status.scan_count >= frame["scan_count"]:
        frame.update(state=status.state.name, scan_count=status.scan_count)
        frame["timing"]["last_exec_us"] = status.last_exec_us
    return frame


def _problem(status: int, error: str, **extra: Any) -> web.Response:
    return web.json_response({"error": error, "problems": [], **extra}, status=status)


class _Routes:
    def __init__(self, api: ApiService) -> None:
        self._api = api
        self._hub = _LiveHub(api)

    async def close(self, app: web.Application) -> None:
        await self._hub.close()

    async def page(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html", headers={
            "Content-Security-Policy": CSP, "Cache-Control": "no-cache",
            "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer"})

    async def net(self, request: web.Request) -> web.Response:
        document = await self._api.board_document()
        net = document.get("net")
        if not isinstance(net, dict):
            return _problem(404, "no program loaded: no net to draw", state=document.get("state"))
        return web.json_response(net)

    async def live(self, request: web.Request) -> web.StreamResponse:
        viewer = self._hub.join()
        response = web.StreamResponse(headers={
            "Content-Type": "text/event-stream", "Cache-Control": "no-cache",
            "X-Accel-Buffering": "no"})
        try:
            await response.prepare(request)
            await response.write(b"retry: 1000\n: connected\n\n")
            while True:
                try:
                    await asyncio.wait_for(viewer.ready.wait(), self._api.heartbeat_s)
                except TimeoutError:
                    await response.write(b": heartbeat\n\n")
                    continue
                viewer.ready.clear()
                frame, viewer.frame = viewer.frame, None
                if viewer.closed:
                    break
                if frame is not None:
                    data = json.dumps(frame, separators=(",", ":"))
                    await response.write(f"event: frame\ndata: {data}\n\n".encode())
        except (ConnectionResetError, asyncio.CancelledError):
            pass  # the page went away
        finally:
            self._hub.leave(viewer)
        return response

    async def forces(self, request: web.Request) -> web.Response:
        document = await self._api.board_document()
        return web.json_response({"forced": document.get("forced") or {}})

    async def force(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        body = await json_body(request)
        entry = ((await self._api.board_document()).get("symbols") or {}).get(name)
        raw = write_raw(name, entry if isinstance(entry, dict) else None, body)
        return await self._reply(await self._api.command(Command.FORCE, symbol=name,
                                                          value=raw))

    async def unforce(self, request: web.Request) -> web.Response:
        name = request.match_info.get("name")
        return await self._reply(await self._api.command(Command.UNFORCE, symbol=name))

    async def _reply(self, reply: Any) -> web.Response:
        if not isinstance(reply, CommandReply):  # pending: the command contract's 202
            return self._api.answer(reply)
        if not reply.ok:
            status = 422 if " refused: " in reply.message else 409
            return _problem(status, reply.message, state=reply.state.name)
        return web.json_response({"ok": True, "message": reply.message,
                                  "state": reply.state.name})
