"""The HTTP management service (aiohttp), hosted in the communication process.

Owns: routes, request validation, JSON errors ({"error", "problems"}, 4xx for bad input,
never a traceback), the bearer-token guard, the body limit, server-sent events fed from
the status board, and mapping scan replies to status codes.
Does not know: how a program compiles or a command acts (the scan process does, behind
the channel), Modbus, the terminal.

Blocking calls (a command waiting for its scan reply, a board read) go through
asyncio.to_thread so that the Modbus slave sharing this loop keeps answering.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import re
import time
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, Protocol

from aiohttp import web

from softplc.api import auth
from softplc.api import web as web_page
from softplc.api.commands import (
    DOWNLOAD_DEADLINE_S,
    KEEP,
    REPLY_GRACE_S,
    CommandBook,
    Outcome,
    Record,
)
from softplc.api.limits import HttpBounds, HttpLimits
from softplc.api.openapi import API_PREFIX, LIFECYCLE_COMMANDS, openapi_document
from softplc.core.image import AddressError, parse_address
from softplc.core.lifecycle import Command
from softplc.core.snapshot import (
    ChannelFull,
    CommandReply,
    CommandRequest,
    HmiWrite,
    NotQueued,
    SnapshotSource,
    SnapshotUnavailable,
    age_ns,
)
from softplc.program import boot
from softplc.program import bundle as bundles

log = logging.getLogger(__name__)

DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 8080
MAX_BODY_BYTES: Final = 1 << 20
COMMAND_TIMEOUT_S: Final = 5.0  # a lifecycle command's deadline; below the client's 10 s
HEARTBEAT_S: Final = 15.0
BOARD_POLL_S: Final = 0.05  # the scan process refreshes the board about every 50 ms
EVENT_QUEUE: Final = 1024  # per client; a slower client loses the oldest and is told
_NAME: Final = re.compile(r"[A-Za-z0-9._-]{1,128}")
_KEY: Final = re.compile(r"[\x21-\x7e]{1,64}")
_TRUE: Final = frozenset({"1", "true", "yes", "on"})
_FALSE: Final = frozenset({"0", "false", "no", "off", ""})
_REFUSED_PROGRAM: Final = "download refused"  # the scan's prefix for a program that failed
# Characters a YAML stream may not hold (YAML 1.1 section 5.1, as PyYAML's reader checks).
_NOT_YAML: Final = re.compile(
    "[^\x09\x0A\x0D\x20-\x7E\x85\xA0-\uD7FF\uE000-\uFFFD\U00010000-\U0010FFFF]")


class CommandChannel(Protocol):
    """What the service needs of softplc.runtime.channel.Channel (client side)."""

    def send_command(self, request: CommandRequest, timeout_s: float = ...,
                     on_late: Callable[[CommandReply], None] | None = ...) -> CommandReply: ...

    def send_hmi_write(self, write: HmiWrite) -> None: ...


class BoardSource(Protocol):
    """What the service needs of softplc.runtime.board.StatusBoard."""

    def read(self) -> dict[str, Any]: ...


class ApiProblem(Exception):
    """A request the service refuses: rendered as {"error", "problems"} with `status`."""

    def __init__(self, status: int, error: str, problems: Iterable[str] = (),
                 headers: Mapping[str, str] | None = None, **extra: Any) -> None:
        super().__init__(error)
        self.status = status
        self.error = error
        self.problems = list(problems)
        self.headers = dict(headers or {})
        self.extra = extra

    def response(self) -> web.Response:
        body = {"error": self.error, "problems": self.problems, **self.extra}
        return web.json_response(body, status=self.status, headers=self.headers)


def _flag(value: str | None, what: str) -> bool:
    text = (value or "").strip().lower()
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise ApiProblem(400, f"{what} must be true or false, not {value!r}")


def _unprintable(text: str, name: str) -> list[str]:
    """Problems for characters no YAML may contain, found before the scan process sees them."""
    problems = []
    for match in itertools.islice(_NOT_YAML.finditer(text), 20):
        line = text.count("\n", 0, match.start()) + 1
        problems.append(f"{name}:{line}: character U+{ord(match.group()):04X} is not allowed "
                        "in YAML")
    return problems


def _program_problems(message: str) -> list[str]:
    """Every problem line of a refused download ("download refused:\\nFILE:LINE: ...")."""
    head, _, rest = message.partition("\n")
    lines = [line.strip() for line in rest.splitlines() if line.strip()]
    return lines or [head.removeprefix(f"{_REFUSED_PROGRAM}:").strip() or head]


@dataclass(eq=False, slots=True)
class _Subscriber:
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


class _EventHub:
    """Polls the board while anyone listens; hands each new event to every subscriber once."""

    def __init__(self, read_board: Callable[[], Awaitable[dict[str, Any]]]) -> None:
        self._read_board = read_board
        self._subscribers: set[_Subscriber] = set()
        self._task: asyncio.Task[None] | None = None
        self._last = 0

    async def subscribe(self, names: frozenset[str], last_id: int | None) -> _Subscriber:
        events = await self._events()
        newest = max((int(e["seq"]) for e in events), default=0)
        sub = _Subscriber(names, newest if last_id is None else min(last_id, newest))
        for event in events:  # replay after Last-Event-ID; nothing otherwise
            sub.offer(event)
        self._subscribers.add(sub)
        if self._task is None or self._task.done():
            self._last = newest
            self._task = asyncio.create_task(self._run(), name="softplc-api-events")
        return sub

    def unsubscribe(self, sub: _Subscriber) -> None:
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


def _sse(event: dict[str, Any]) -> bytes:
    return f"id: {event['seq']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n".encode()


class ApiServer:
    """The service on one asyncio loop. `port=0` picks a free port (see `bound_port`)."""

    def __init__(self, channel: CommandChannel, snapshots: SnapshotSource, board: BoardSource,
                 *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, state_dir: Path,
                 token_required: bool | None = None, heartbeat_s: float = HEARTBEAT_S,
                 command_timeout_s: float = COMMAND_TIMEOUT_S,
                 limits: HttpLimits | None = None) -> None:
        self.host = host
        self.port = port
        self.state_dir = Path(state_dir)
        self.token_required = auth.token_required(host, token_required)
        self.heartbeat_s = heartbeat_s
        self.command_timeout_s = command_timeout_s
        self._channel = channel
        self._snapshots = snapshots
        self._board = board
        self._book = CommandBook()  # ids (never 0: the scan's own), deadlines, outcomes
        self._token: str | None = None
        self._hub = _EventHub(self._board_document)
        self._runner: web.AppRunner | None = None
        self.bounds = HttpBounds(limits)  # connection cap, header and body timeouts

    @property
    def token_file(self) -> Path | None:
        """Where the token is kept (never the token itself), or None when none is needed."""
        return self.state_dir / auth.TOKEN_FILE if self.token_required else None

    @property
    def bound_port(self) -> int:
        if self._runner is None or not self._runner.addresses:
            raise RuntimeError("the API server is not started")
        port: int = self._runner.addresses[0][1]
        return port

    async def start(self) -> None:
        if self.token_required:
            self._token = await asyncio.to_thread(auth.load_or_create_token, self.state_dir)
        self._runner = self.bounds.runner(self.build_app(), shutdown_timeout=2.0,
                                          access_log_format='%a "%r" %s %b %Tfs')
        await self._runner.setup()
        await self.bounds.site(self._runner, self.host, self.port).start()
        log.info("HTTP API on %s:%d (token %s)", self.host, self.bound_port,
                 "required" if self.token_required else "not required")

    async def stop(self) -> None:
        await self._hub.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    def build_app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY_BYTES,
                              middlewares=[self._errors, self._guard])
        p = API_PREFIX
        app.router.add_get("/healthz", self._healthz)
        app.router.add_get(f"{p}/status", self._status)
        app.router.add_post(f"{p}/program", self._download)
        app.router.add_get(f"{p}/program", self._upload)
        for command in LIFECYCLE_COMMANDS:
            app.router.add_post(f"{p}/{command}", self._lifecycle)
        app.router.add_get(f"{p}/commands/{{id}}", self._command_outcome)
        app.router.add_get(f"{p}/symbols", self._symbols)
        app.router.add_get(f"{p}/symbols/{{name}}", self._symbol)
        app.router.add_put(f"{p}/symbols/{{name}}", self._write_symbol)
        app.router.add_get(f"{p}/events", self._events)
        app.router.add_get(f"{p}/openapi.json", self._openapi)
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
        if self._token is None and not auth.host_header_is_loopback(host):
            raise ApiProblem(403, "this service answers requests to a loopback host only")
        if not auth.same_origin(request.headers.get("Origin"), host):
            raise ApiProblem(403, "cross-origin requests are refused")
        public = web_page.is_public(request.method, request.path)  # the page, to ask a token
        if self._token is not None and not public and not auth.bearer_matches(
                request.headers.get("Authorization"), self._token):
            raise ApiProblem(401, "missing or wrong bearer token (see STATE_DIR/api_token)",
                             headers={"WWW-Authenticate": 'Bearer realm="softplc"'})
        if (request.content_length or 0) > MAX_BODY_BYTES:
            raise ApiProblem(413, f"request body larger than {MAX_BODY_BYTES} bytes")
        return await handler(request)

    # -- plumbing ---------------------------------------------------------------------------

    async def _board_document(self) -> dict[str, Any]:
        try:
            document = await asyncio.to_thread(self._board.read)
        except TimeoutError as exc:
            raise ApiProblem(503, f"status board unavailable: {exc}") from None
        return document

    async def _command(self, command: Command, text: str | None = None,
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
            reply = await asyncio.to_thread(self._channel.send_command, request,
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
            snapshot = self._snapshots.latest()
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

    def _answer(self, reply: CommandReply | Record) -> web.Response:
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

    @staticmethod
    def _key(request: web.Request) -> str | None:
        key = request.headers.get("Idempotency-Key")
        if key is not None and not _KEY.fullmatch(key):
            raise ApiProblem(400, "Idempotency-Key must be 1 to 64 printable ASCII characters")
        return key

    # -- handlers ---------------------------------------------------------------------------

    async def _healthz(self, request: web.Request) -> web.Response:
        return web.json_response({"status": "ok"})

    async def _openapi(self, request: web.Request) -> web.Response:
        return web.json_response(openapi_document())

    async def _status(self, request: web.Request) -> web.Response:
        document = await self._board_document()
        events = document.get("events") or []
        status = {k: v for k, v in document.items() if k not in ("symbols", "events")}
        status.setdefault("program", None)
        status.setdefault("marking", {})
        status["board_scan_count"] = status.get("scan_count", 0)
        status["stale"], status["snapshot_age_ms"] = True, None
        with contextlib.suppress(SnapshotUnavailable):
            # The snapshot follows every scan, the board every ~50 ms: a command's new state
            # shows at once. Marking and timing stay the board's (board_scan_count).
            snapshot = self._snapshots.latest()
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
        status["last_event_seq"] = max(
            (e["seq"] for e in events if isinstance(e, dict) and isinstance(e.get("seq"), int)),
            default=0)
        return web.json_response(status)

    async def _download(self, request: web.Request) -> web.Response:
        online = _flag(request.query.get("online", request.headers.get("X-Softplc-Online")),
                       "online")
        replace = _flag(request.query.get("replace"), "replace")
        dry_run = _flag(request.query.get("dry_run"), "dry_run")
        name = request.query.get("name")
        if name is not None and not _NAME.fullmatch(name):
            raise ApiProblem(400, "name must be a plain file name (letters, digits, . _ -)")
        body = await request.read()
        if request.content_type == bundles.CONTENT_TYPE or bundles.is_bundle(body):
            try:  # checked here, so that a bad archive never reaches the scan process
                bundle = await asyncio.to_thread(bundles.unpack, body)
            except bundles.BundleError as exc:
                raise ApiProblem(422, "download refused: unusable bundle", [str(exc)]) from None
            reply = await self._command(Command.DOWNLOAD, None, bundle.program, online,
                                        self._key(request), replace=replace, bundle=body,
                                        dry_run=dry_run)
            return self._download_answer(reply)
        try:
            text = body.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ApiProblem(400, f"the program must be UTF-8 text ({exc.reason} at byte "
                                  f"{exc.start})") from None
        if not text.strip():
            raise ApiProblem(422, "download refused: empty program",
                             [f"{name or 'program'}:1: the request body holds no program"])
        if problems := _unprintable(text, name or "program"):
            raise ApiProblem(422, "download refused: not YAML text", problems)
        reply = await self._command(Command.DOWNLOAD, text, name, online, self._key(request),
                                    replace=replace, dry_run=dry_run)
        return self._download_answer(reply)

    def _download_answer(self, reply: CommandReply | Record) -> web.Response:
        if isinstance(reply, CommandReply) and not reply.ok and reply.message.startswith(
                _REFUSED_PROGRAM):
            raise ApiProblem(422, reply.message.partition("\n")[0].rstrip(":"),
                             _program_problems(reply.message), state=reply.state.name,
                             id=reply.id)
        if isinstance(reply, CommandReply) and reply.ok and reply.detail is not None:
            return web.json_response({"ok": True, "message": reply.message, "id": reply.id,
                                      "state": reply.state.name, "plan": reply.detail})
        return self._answer(reply)

    async def _upload(self, request: web.Request) -> web.Response:
        """The running program's bundle, byte for byte as it was downloaded."""
        try:
            program = await asyncio.to_thread(boot.load, self.state_dir)
        except boot.BootUnreadable as exc:
            raise ApiProblem(409, f"no program to upload: {exc}") from None
        running = (await self._board_document()).get("program_hash")
        if program is None or program.bundle is None or not running:
            raise ApiProblem(404, "no program to upload: the PLC runs none, or its program "
                             f"came without a bundle (state directory {self.state_dir})")
        if program.program_hash and program.program_hash != running:
            raise ApiProblem(409, "the running program's bundle is not stored yet (the last "
                             "accepted download is being written); try again", headers={
                                 "Retry-After": "1"})
        return web.Response(body=program.bundle, content_type=bundles.CONTENT_TYPE, headers={
            "Content-Disposition": f'attachment; filename="{Path(program.filename).stem}.zip"'})

    async def _lifecycle(self, request: web.Request) -> web.Response:
        command = Command(request.path.rsplit("/", 1)[1])
        return self._answer(await self._command(command, key=self._key(request)))

    async def _symbol_table(self) -> dict[str, dict[str, Any]]:
        symbols = (await self._board_document()).get("symbols") or {}
        return {k: v for k, v in symbols.items() if isinstance(v, dict)}

    def _view(self, name: str, entry: Mapping[str, Any], image: Any) -> dict[str, Any]:
        value = entry.get("value", 0)
        if image is not None:
            with contextlib.suppress(AddressError, TypeError, KeyError):
                value = image.get(parse_address(str(entry["address"])))
        if entry.get("type") == "bool":
            value = bool(value)
        return {"name": name, "address": entry.get("address"), "type": entry.get("type"),
                "direction": entry.get("direction"), "value": value}

    def _image(self) -> tuple[int, Any]:
        try:
            snapshot = self._snapshots.latest()
        except SnapshotUnavailable:
            return 0, None  # the board's values (up to ~50 ms old) stand in
        return snapshot.seq, snapshot.image

    async def _symbols(self, request: web.Request) -> web.Response:
        table = await self._symbol_table()
        seq, image = self._image()
        return web.json_response({"snapshot_seq": seq, "symbols": {
            name: self._view(name, entry, image) for name, entry in table.items()}})

    async def _lookup(self, request: web.Request) -> tuple[str, dict[str, Any]]:
        name = request.match_info["name"]
        entry = (await self._symbol_table()).get(name)
        if entry is None:
            raise ApiProblem(404, f"no symbol {name!r} in the loaded program")
        return name, entry

    async def _symbol(self, request: web.Request) -> web.Response:
        name, entry = await self._lookup(request)
        return web.json_response(self._view(name, entry, self._image()[1]))

    async def _write_symbol(self, request: web.Request) -> web.Response:
        name, entry = await self._lookup(request)
        if entry.get("direction") == "in":
            raise ApiProblem(403, f"symbol {name} ({entry.get('address')}) is an input: "
                                  "inputs belong to the drivers")
        if entry.get("hmi_writable") is False:
            raise ApiProblem(403, f"symbol {name} is declared hmi_writable: false")
        value = _write_value(name, entry, await _json_body(request))
        try:
            address = parse_address(str(entry.get("address")))
        except AddressError as exc:
            raise ApiProblem(409, f"symbol {name} has no usable address: {exc}") from None
        try:
            self._channel.send_hmi_write(HmiWrite(address, (int(value),)))
        except ChannelFull as exc:
            raise ApiProblem(503, str(exc), headers={"Retry-After": "1"}) from None
        return web.json_response({"name": name, "address": str(address), "value": value,
                                  "queued": True}, status=202)

    async def _events(self, request: web.Request) -> web.StreamResponse:
        names = frozenset(n.strip() for n in request.query.get("names", "").split(",")
                          if n.strip())
        last_id = request.headers.get("Last-Event-ID")
        if last_id is not None and not last_id.strip().isdigit():
            raise ApiProblem(400, "Last-Event-ID must be an event seq (a number)")
        sub = await self._hub.subscribe(names, None if last_id is None else int(last_id))
        response = web.StreamResponse(headers={
            "Content-Type": "text/event-stream", "Cache-Control": "no-cache",
            "X-Accel-Buffering": "no"})
        try:
            await response.prepare(request)
            await response.write(b"retry: 1000\n: connected\n\n")
            await self._stream(sub, response)
        except (ConnectionResetError, asyncio.CancelledError):
            pass  # the client went away
        finally:
            self._hub.unsubscribe(sub)
        return response

    async def _stream(self, sub: _Subscriber, response: web.StreamResponse) -> None:
        reported = 0
        while True:
            try:
                event = await asyncio.wait_for(sub.queue.get(), self.heartbeat_s)
            except TimeoutError:
                await response.write(b": heartbeat\n\n")
                continue
            if event is None:
                return  # the server stops
            if sub.dropped != reported:
                reported = sub.dropped
                await response.write(f"event: overflow\ndata: {json.dumps({'dropped': reported})}"
                                     "\n\n".encode())
            await response.write(_sse(event))


async def _json_body(request: web.Request) -> Any:
    try:
        return json.loads(await request.read())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ApiProblem(400, f"the body must be JSON like {{\"value\": 1}}: {exc}") from None


def _write_value(name: str, entry: Mapping[str, Any], body: Any) -> bool | int:
    """The value of a symbol write, checked against the symbol's type."""
    if not isinstance(body, dict) or "value" not in body:
        raise ApiProblem(422, 'the body must be a JSON object {"value": n}')
    value = body["value"]
    if entry.get("type") == "bool":
        if isinstance(value, bool) or (type(value) is int and value in (0, 1)):
            return bool(value)
        raise ApiProblem(422, f"symbol {name} is a bool: value must be true/false or 0/1, "
                              f"not {json.dumps(value)[:40]}")
    if type(value) is int and 0 <= value <= 0xFFFF:
        return value
    raise ApiProblem(422, f"symbol {name} is a word: value must be an integer 0..65535, "
                          f"not {json.dumps(value)[:40]}")
