"""The recent past over HTTP (issue 32): `GET /api/v1/history`, read-only (viewer).

Owns: the sampler, a thread of this (the HTTP) process that follows the snapshot the scan
process publishes after every scan and the status board (about every 50 ms) into a History
(historyring.py), and the route that answers a window of it. The scan pays nothing: it
publishes as it always did; a scan this process does not see in time (a loaded machine, a
scan period under about 2 ms) is missing from the history and reported as a gap.
Does not know: the scan loop, how the snapshot and the board are shared (it is handed a
SnapshotSource and a BoardSource).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from typing import Final

from aiohttp import web

from softplc.api.historyring import MAX_BYTES, MAX_SCANS, History, Layout
from softplc.api.openapi import API_PREFIX
from softplc.api.problems import ApiProblem
from softplc.api.service import ApiService, BoardSource
from softplc.core.snapshot import Snapshot, SnapshotSource, SnapshotUnavailable

log = logging.getLogger(__name__)

ENV_SCANS: Final = "SOFTPLC_HISTORY_SCANS"  # scans kept; 0: no history (docs/debug.md)
BOARD_EVERY_NS: Final = 50_000_000  # the scan process refreshes the board about this often
MIN_WAIT_S: Final = 0.001  # the sampler's fastest poll: scans under ~2 ms leave gaps
MAX_WAIT_S: Final = 0.05
MAX_NAMES: Final = 64  # symbols and places per request
SAMPLING: Final = ("the HTTP process samples the snapshot published after each scan and the "
                   "status board (about every 50 ms); values are per sampled scan, marking, "
                   "fired and forces per board sample; scans it did not see are in gaps")


def scans_wanted() -> int:
    """Scans to keep, from the environment (default MAX_SCANS; 0 turns the history off)."""
    try:
        return max(0, int(os.environ.get(ENV_SCANS, MAX_SCANS)))
    except ValueError:
        return MAX_SCANS


class Sampler:
    """Follows snapshot and board into a History of the running program, on its own thread
    (a busy event loop must not make it miss scans)."""

    def __init__(self, snapshots: SnapshotSource, board: BoardSource, max_scans: int,
                 max_bytes: int = MAX_BYTES) -> None:
        self._snapshots = snapshots
        self._board = board
        self.max_scans = max_scans
        self.max_bytes = max_bytes
        self.history: History | None = None
        self._board_ns = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self.max_scans and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="softplc-history",
                                            daemon=True)
            self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
            self._thread = None

    def _run(self) -> None:
        wait_s = MIN_WAIT_S
        while not self._stop.wait(wait_s):
            try:
                due_ns = self.step(time.monotonic_ns())
            except Exception:  # a bug here must not end the sampling for good
                log.exception("history sampler")
                due_ns = time.monotonic_ns() + int(MAX_WAIT_S * 1e9)
            # from the clock after the step: a board read (~1 ms of JSON) is not slept again
            wait_s = min(max((due_ns - time.monotonic_ns()) / 1e9, MIN_WAIT_S), MAX_WAIT_S)

    def step(self, now_ns: int) -> int:
        """Take what is new; when to look again (CLOCK_MONOTONIC ns)."""
        idle_ns = now_ns + int(MAX_WAIT_S * 1e9)
        try:
            snapshot = self._snapshots.latest()
        except SnapshotUnavailable:
            return idle_ns
        status = snapshot.status
        history = self.history
        if history is None or history.layout.program_hash != status.program_hash:
            history = self._renew(status.program_hash)
            if history is None:
                return idle_ns
        last = history.last_scan()
        if last is not None and status.scan_count < last:  # the PLC started again: anew
            history = self.history = History(history.layout, self.max_scans, self.max_bytes)
            last = None
        if status.scan_count != last:
            history.add_scan(status.scan_count, status.published_ns or now_ns,
                             int(status.state), status.forced, snapshot.image)
        if now_ns - self._board_ns >= BOARD_EVERY_NS:
            self._board_ns = now_ns
            self._take_board(history, now_ns)
        return _next_look(snapshot, now_ns)

    def _renew(self, program_hash: str) -> History | None:
        """A new History once the board shows the program the snapshot runs."""
        if not program_hash:
            self.history = None
            return None
        with contextlib.suppress(TimeoutError, ValueError):
            layout = Layout.of_board(self._board.read())
            if layout is not None and layout.program_hash == program_hash:
                self.history = History(layout, self.max_scans, self.max_bytes)
                return self.history
        return None

    def _take_board(self, history: History, now_ns: int) -> None:
        try:
            doc = self._board.read()
        except (TimeoutError, ValueError):
            return
        if doc.get("program_hash") != history.layout.program_hash:
            return
        live = doc.get("net_live") or {}
        history.add_board(int(doc.get("scan_count") or 0), now_ns, doc.get("marking") or {},
                          live.get("fired_counts") or {}, doc.get("forced") or {})


def _next_look(snapshot: Snapshot, now_ns: int) -> int:
    """A quarter period after the next publish is due: one look a scan while the scan keeps
    time; a quarter period from now when it is late."""
    period_ns = snapshot.status.period_us * 1000 or BOARD_EVERY_NS
    due = (snapshot.status.published_ns or now_ns) + period_ns + period_ns // 4
    return due if due > now_ns else now_ns + period_ns // 4


def register(app: web.Application, api: ApiService, board: BoardSource) -> None:
    """Add the history route to `app` and run its sampler while the app runs (server.py's
    build_app calls this once)."""
    sampler = Sampler(api.snapshots, board, scans_wanted())
    routes = _Routes(sampler)

    async def start(app: web.Application) -> None:
        sampler.start()

    async def stop(app: web.Application) -> None:
        await asyncio.to_thread(sampler.stop)

    app.on_startup.append(start)
    app.on_cleanup.append(stop)
    app.router.add_get(f"{API_PREFIX}/history", routes.history)


def _names(request: web.Request, key: str, known: tuple[str, ...], what: str) -> list[str]:
    """The names asked for in `key` (a,b,c), each known; all known (the first MAX_NAMES)
    when the parameter is absent."""
    text = request.query.get(key)
    if text is None:
        return list(known[:MAX_NAMES])
    names = [n for n in (part.strip() for part in text.split(",")) if n]
    if len(names) > MAX_NAMES:
        raise ApiProblem(400, f"at most {MAX_NAMES} {what}s at a time, not {len(names)}")
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ApiProblem(400, f"no {what} {', '.join(map(repr, unknown[:5]))} in the program",
                         [f"{what}s: {', '.join(known[:50])}"])
    return names


class _Routes:
    def __init__(self, sampler: Sampler) -> None:
        self._sampler = sampler

    async def history(self, request: web.Request) -> web.Response:
        sampler = self._sampler
        if not sampler.max_scans:
            raise ApiProblem(404, f"the history is off ({ENV_SCANS}=0 where softplc runs)")
        try:
            since = int(request.query.get("since", "-1"))
        except ValueError:
            raise ApiProblem(400, "since must be a scan number") from None
        history = sampler.history
        if history is None:
            raise ApiProblem(404, "no history yet: no program is running, or it has just "
                                  "been loaded", headers={"Retry-After": "1"})
        layout = history.layout
        symbols = _names(request, "symbols", tuple(s[0] for s in layout.symbols), "symbol")
        places = _names(request, "places", layout.places, "place")
        offset_ns = time.time_ns() - time.monotonic_ns()
        window = await asyncio.to_thread(history.window, since, symbols, places, offset_ns)
        scans, board = history.max_rows
        return web.json_response({
            "program": layout.program, "program_hash": layout.program_hash, "since": since,
            **window, "sampling": SAMPLING,
            "capacity": {"scans": scans, "board_samples": board, "bytes": history.nbytes,
                         "max_bytes": sampler.max_bytes}})
