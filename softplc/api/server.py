"""The HTTP management service (aiohttp), hosted in the communication process.

Owns: the application (its routes: program.py, symbols.py, events.py, web.py and
accessroutes.py add theirs), the guard (Host/Origin checks, then the route's role against
the request's principal and the audit record of a change: accessroutes.py), TLS when
asked (tls.py; `softplc run` hands its options over in STATE_DIR/security.json), the body
limit, turning any failure into a JSON error ({"error", "problems"}, 4xx for bad input,
never a traceback), sending lifecycle commands with an id and a deadline (api/commands.py
keeps their outcomes) and mapping scan replies to status codes, and the status document.
Does not know: how a program compiles or a command acts (the scan process does, behind
the channel), Modbus, the terminal, the runtime (it is handed a channel, a snapshot source
and a board; their contract is core/snapshot.py).

Blocking calls (a command waiting for its scan reply, a board read) go through
asyncio.to_thread so that the Modbus slave sharing this loop keeps answering.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from softplc.api import accessroutes, debug, history, programs, secopts, symbols
from softplc.api import web as web_page
from softplc.api.access import PRINCIPAL, Gate
from softplc.api.commands import (
    DOWNLOAD_DEADLINE_S,
    KEEP,
    REPLY_GRACE_S,
    CommandBook,
    Outcome,
    Record,
)
from softplc.api.events import EventHub
from softplc.api.limits import HttpBounds, HttpLimits, Kind
from softplc.api.openapi import API_PREFIX, LIFECYCLE_COMMANDS, openapi_document
from softplc.api.problems import MAX_JSON_BYTES, ApiProblem, idempotency_key
from softplc.api.service import BoardSource, CommandChannel
from softplc.api.signed import DownloadSigning
from softplc.api.tlsproto import TlsRunner
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.snapshot import (
    ChannelFull,
    CommandReply,
    NotQueued,
    SnapshotSource,
    SnapshotUnavailable,
    age_ns,
)
from softplc.security import auth, tls
from softplc.security.roles import Act, Role

log = logging.getLogger(__name__)

DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 8080
MAX_BODY_BYTES: Final = 1 << 20
COMMAND_TIMEOUT_S: Final = 5.0  # a lifecycle command's deadline; below the client's 10 s
HEARTBEAT_S: Final = 15.0
# Endless responses, pooled (api/limits.py): events do not starve pages. The admin's audit
# stream shares the events' pool.
STREAM_POOLS: Final = {f"{API_PREFIX}/events": "events", f"{API_PREFIX}/live": "live",
                       f"{API_PREFIX}/audit/events": "events"}
# Always served, whatever streams and other requests hold: the operator's way in and out.
PRIORITY_PATHS: Final = frozenset({"/healthz", "/", "/index.html", f"{API_PREFIX}/status",
                                   f"{API_PREFIX}/stop", f"{API_PREFIX}/kill"})


def request_class(method: str, path: str, has_body: bool) -> tuple[Kind, str]:
    """The class a request is bounded in (docs/api.md, "Connections and request classes").
    A request with a body is never a priority one: a trickled body would hold the reserve."""
    if method == "GET" and path in STREAM_POOLS:
        return Kind.STREAM, STREAM_POOLS[path]
    if not has_body and method in ("GET", "HEAD", "POST") and (
            path in PRIORITY_PATHS or path.startswith(("/static/", f"{API_PREFIX}/commands/"))):
        return Kind.PRIORITY, ""
    return Kind.ORDINARY, ""


class ApiServer:
    """The service on one asyncio loop. `port=0` picks a free port (see `bound_port`)."""

    def __init__(self, channel: CommandChannel, snapshots: SnapshotSource, board: BoardSource,
                 *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, state_dir: Path,
                 token_required: bool | None = None, heartbeat_s: float = HEARTBEAT_S,
                 command_timeout_s: float = COMMAND_TIMEOUT_S,
                 limits: HttpLimits | None = None,
                 security: secopts.SecuritySettings | None = None) -> None:
        self.host = host
        self.port = port
        self.state_dir = Path(state_dir)
        self.token_required = auth.token_required(host, token_required)
        self.heartbeat_s = heartbeat_s
        self.command_timeout_s = command_timeout_s
        self.channel = channel
        self.snapshots = snapshots
        self._board = board
        self._book = CommandBook()  # ids (never 0: the scan's own), deadlines, outcomes
        # Without credentials: a viewer on loopback, nobody when bound elsewhere (or told so).
        self.gate = Gate(self.state_dir, "", None if self.token_required else Role.VIEWER)
        self._indexed: Path | None = None
        self._hub = EventHub(self.board_document)
        self._runner: web.AppRunner | None = None
        # Connection cap, request classes, header and body timeouts.
        self.bounds = HttpBounds(limits, request_class, pools=len(set(STREAM_POOLS.values())))
        # None: what `softplc run` asked for (none: plain HTTP, STATE_DIR/trusted_keys).
        self.security = security or secopts.load(self.state_dir)
        self.signing = DownloadSigning(self.state_dir, self.security.trusted_dir(self.state_dir),
                                       required=self.security.trusted_keys is not None)
        self.tls_cert: Path | None = None  # the certificate served, when TLS is on

    @property
    def token_file(self) -> Path:
        """Where the owner's key is kept (never the key itself)."""
        return self.state_dir / auth.TOKEN_FILE

    @property
    def bound_port(self) -> int:
        if self._runner is None or not self._runner.addresses:
            raise RuntimeError("the API server is not started")
        port: int = self._runner.addresses[0][1]
        return port

    async def start(self) -> None:
        self.gate.set_owner(await asyncio.to_thread(auth.load_or_create_token, self.state_dir))
        runner = self.bounds.runner(self.build_app(), shutdown_timeout=2.0,
                                    access_log_format='%a "%r" %s %b %Tfs')
        if self.security.tls.wanted(self.host):
            cert, key, made = await asyncio.to_thread(tls.certificate, self.security.tls,
                                                      self.state_dir, self.host)
            runner = TlsRunner.around(runner, tls.server_context(cert, key))
            self.tls_cert = cert
            log.info("HTTPS with %s certificate %s (SHA-256 %s)", "a new" if made else "the",
                     cert, await asyncio.to_thread(tls.fingerprint, cert))
        self._runner = runner
        await self._runner.setup()
        await self.bounds.site(self._runner, self.host, self.port).start()
        with contextlib.suppress(OSError):  # the owner's CLI then gives --state-dir itself
            self._indexed = auth.register_server(self.bound_port, self.state_dir)
        await self.gate.chain()  # the first check of the audit chain starts now, in a thread
        log.info("HTTP API on %s://%s:%d (without credentials: %s)",
                 "https" if self.tls_cert else "http",
                 f"[{self.host}]" if ":" in self.host else self.host, self.bound_port,
                 "nothing" if self.token_required else "read only")

    async def stop(self) -> None:
        auth.unregister_server(self._indexed)
        self._indexed = None
        await self._hub.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        await self.gate.close()  # refusals still counted: written now

    def build_app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY_BYTES,
                              middlewares=[self._errors, self._guard])
        p = API_PREFIX
        app.router.add_get("/healthz", self._healthz)
        app.router.add_get(f"{p}/status", self._status)
        for command in LIFECYCLE_COMMANDS:
            app.router.add_post(f"{p}/{command}", self._lifecycle)
        app.router.add_get(f"{p}/commands/{{id}}", self._command_outcome)
        app.router.add_get(f"{p}/events", self._events)
        app.router.add_get(f"{p}/openapi.json", self._openapi)
        accessroutes.register(app, self.gate, self.heartbeat_s)  # login, whoami, audit
        programs.register(app, self, self.signing)  # download and upload
        symbols.register(app, self)
        debug.register(app, self)  # why (docs/debug.md)
        history.register(app, self, self._board)  # the recent past (docs/debug.md)
        web_page.register(app, self)  # the operator's page, live stream, forcing (docs/web.md)
        return app

    # -- middlewares ------------------------------------------------------------------------

    @web.middleware
    async def _errors(self, request: web.Request,
                      handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                      ) -> web.StreamResponse:
        try:
            return await handler(request)
        except ApiProblem as problem:
            failure = problem
        except web.HTTPException as exc:
            if exc.status < 400:
                raise
            headers = {k: v for k, v in exc.headers.items() if k == "Allow"}
            failure = ApiProblem(exc.status, f"{exc.reason}: {request.method} "
                                 f"{request.path[:200]}", headers=headers)
        except Exception:
            log.exception("internal error in %s %s", request.method, request.path)
            failure = ApiProblem(500, "internal error (logged by the server)")
        return failure.response()

    @web.middleware
    async def _guard(self, request: web.Request,
                     handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                     ) -> web.StreamResponse:
        if request.path == "/healthz":
            return await handler(request)
        host = request.headers.get("Host")
        if self.gate.anonymous is not None and not self.gate.has_credentials(request) \
                and not auth.host_header_is_loopback(host):
            raise ApiProblem(403, "this service answers requests to a loopback host only")
        if not auth.same_origin(request.headers.get("Origin"), host,
                                "https" if request.secure else "http"):
            raise ApiProblem(403, "cross-origin requests are refused")
        who = await accessroutes.admit(self.gate, request)  # 401, 403 (roles.py), 429
        PRINCIPAL.set(who)
        if (request.content_length or 0) > MAX_BODY_BYTES:
            raise ApiProblem(413, f"request body larger than {MAX_BODY_BYTES} bytes")
        if request.method == "PUT" and (request.content_length or 0) > MAX_JSON_BYTES:
            # Every PUT is a JSON value write: refused before the body is read, not after.
            raise ApiProblem(413, f"JSON body of {request.content_length} bytes: at most "
                                  f"{MAX_JSON_BYTES}")
        return await accessroutes.audited(self.gate, request, who, handler)

    # -- plumbing ---------------------------------------------------------------------------

    async def board_document(self) -> dict[str, Any]:
        try:
            document = await asyncio.to_thread(self._board.read)
        except TimeoutError as exc:
            raise ApiProblem(503, f"status board unavailable: {exc}") from None
        return document

    async def command(self, command: Command, text: str | None = None,
                      name: str | None = None, online: bool = False,
                      key: str | None = None, symbol: str | None = None,
                      value: int = 0, replace: bool = False, bundle: bytes | None = None,
                      dry_run: bool = False) -> CommandReply | Record:
        """Send a command with an id and a deadline. Returns its reply, or its pending Record
        when no reply came in time (it is then applied before its deadline or never)."""
        if key is not None and (known := self._book.by_key(key)) is not None:
            return known  # a retry: the first attempt's outcome, never a second command
        self._refuse_if_stale()
        deadline_s = DOWNLOAD_DEADLINE_S if command is Command.DOWNLOAD else self.command_timeout_s
        request = self._book.request(command, deadline_s, key, program_text=text,
                                     program_path=name, online=online, symbol=symbol,
                                     value=value, replace=replace, bundle=bundle,
                                     dry_run=dry_run)
        try:
            reply = await asyncio.to_thread(self.channel.send_command, request,
                                            deadline_s + REPLY_GRACE_S, self._book.late)
        except (NotQueued, ChannelFull) as exc:
            self._book.drop(request.id, f"not queued: {exc}")
            raise ApiProblem(503, f"{command.value} not sent, never applied: {exc}",
                             headers={"Retry-After": "1"}) from None
        except TimeoutError:
            record = self._book.get(request.id)
            assert record is not None
            return record
        self._book.settle(reply)
        return reply

    def _refuse_if_stale(self) -> None:
        """A frozen or restarting scan process cannot take a command now: say so at once
        instead of queueing it for some later moment."""
        with contextlib.suppress(SnapshotUnavailable):
            snapshot = self.snapshots.latest()
            if snapshot.status.stale:
                age = age_ns(snapshot, time.monotonic_ns())
                raise ApiProblem(503, "PLC not responding: no scan published for "
                                 + (f"{age / 1e6:.0f} ms" if age >= 0 else "ever")
                                 + "; the command was not sent", headers={"Retry-After": "1"},
                                 stale=True)

    @staticmethod
    def _pending(record: Record) -> web.Response:
        body = {"ok": False, "pending": True, **record.as_dict(),
                "outcome": f"{API_PREFIX}/commands/{record.id}",
                "message": record.message or (
                    f"no reply yet: {record.command} is applied before its deadline or never; "
                    f"ask {API_PREFIX}/commands/{record.id} for the outcome")}
        status = 202 if record.outcome is Outcome.PENDING else 200
        return web.json_response(body, status=status,
                                 headers={"Location": f"{API_PREFIX}/commands/{record.id}"})

    def answer(self, reply: CommandReply | Record) -> web.Response:
        """A reply, or a retried command's record, as the HTTP answer."""
        if isinstance(reply, Record):
            if reply.outcome is Outcome.APPLIED:
                return web.json_response({"ok": True, "message": reply.message,
                                          "state": reply.state, "id": reply.id})
            if reply.outcome in (Outcome.REFUSED, Outcome.EXPIRED):
                raise ApiProblem(409, reply.message, state=reply.state, id=reply.id,
                                 outcome=reply.outcome.value)
            return self._pending(reply)
        if not reply.ok:
            raise ApiProblem(409, reply.message, state=reply.state.name, id=reply.id,
                             outcome="expired" if reply.expired else "refused")
        return web.json_response({"ok": True, "message": reply.message,
                                  "state": reply.state.name, "id": reply.id})

    async def _command_outcome(self, request: web.Request) -> web.Response:
        try:
            record = self._book.get(int(request.match_info["id"]))
        except ValueError:
            record = None
        if record is None:
            raise ApiProblem(404, f"no recent command {request.match_info['id'][:40]} "
                             f"(the last {KEEP} are kept)")
        return web.json_response(record.as_dict())

    # -- handlers ---------------------------------------------------------------------------

    async def _healthz(self, request: web.Request) -> web.Response:
        return web.json_response({"status": "ok"})

    async def _openapi(self, request: web.Request) -> web.Response:
        return web.json_response(openapi_document())

    async def _status(self, request: web.Request) -> web.Response:
        document = await self.board_document()
        events = document.get("events") or []
        status = {k: v for k, v in document.items() if k not in ("symbols", "events")}
        status.setdefault("program", None)
        status.setdefault("marking", {})
        status["board_scan_count"] = status.get("scan_count", 0)
        status["stale"], status["snapshot_age_ms"] = True, None
        with contextlib.suppress(SnapshotUnavailable):
            # The snapshot follows every scan, the board every ~50 ms: a command's new state
            # shows at once. Marking and timing stay the board's (board_scan_count).
            snapshot = self.snapshots.latest()
            s = snapshot.status
            age = age_ns(snapshot, time.monotonic_ns())
            status["stale"] = s.stale
            status["snapshot_age_ms"] = round(age / 1e6, 1) if age >= 0 else None
            if s.scan_count >= status["board_scan_count"] or "state" not in status:
                status.update(state=s.state.name, scan_count=s.scan_count,
                              fault_code=s.fault_code)
                status.setdefault("program_hash", s.program_hash or None)
                status.setdefault("timing", {"p99_lateness_us": s.p99_lateness_us,
                                             "overruns": s.overruns})
        status["program_signer"] = await self.signing.running_signer(
            status.get("program_hash"))
        status["signatures"] = (await asyncio.to_thread(self.signing.keys)).status()
        status["http"] = self.bounds.report()  # refusals counted here, not logged one by one
        status["audit"] = await self.gate.chain()  # "ok": false names the first bad record
        status["last_event_seq"] = max(
            (e["seq"] for e in events if isinstance(e, dict) and isinstance(e.get("seq"), int)),
            default=0)
        return web.json_response(status)

    async def _lifecycle(self, request: web.Request) -> web.Response:
        command = Command(request.path.rsplit("/", 1)[1])
        return self.answer(await self.command(command, key=idempotency_key(request)))

    async def _events(self, request: web.Request) -> web.StreamResponse:
        who = PRINCIPAL.get()

        def revoked() -> str | None:
            decision = self.gate.decide(who, Act.READ) if who is not None else None
            return None if decision is None or decision.allowed else decision.reason()

        return await self._hub.serve(request, self.heartbeat_s, revoked)

    def image(self) -> tuple[int, ProcessImage | None]:
        """The latest snapshot's seq and image; (0, None) when none can be read."""
        try:
            snapshot = self.snapshots.latest()
        except SnapshotUnavailable:
            return 0, None  # the board's values (up to ~50 ms old) stand in
        return snapshot.seq, snapshot.image

