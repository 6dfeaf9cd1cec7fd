"""The OPC UA server of the communication process (asyncua), beside Modbus and the HTTP API.

Owns: starting/stopping asyncua on its endpoints (secure.py sets up certificates, trust and
logins), who may do what (access.py: each session's role; writes and method calls need the
role the same command needs over HTTP), the audit records of writes and method calls, symbol
writes (checked against the Modbus write policy and the node's DataType, converted to the
symbol's raw bits by typed.py (core/present.py's `accepted`), then journaled
through the channel like Modbus and API writes, never stored in the address space), polling
the snapshot (every `poll_s`) and the status board (every `board_poll_s`) and
pushing only changed values, rebuilding the program's nodes when a download changes the
program hash, and turning board events, downloads, state changes and faults into OPC UA events
(access.py decides who may act; mirror.py keeps the address space in step with the PLC).
Does not know: the scan, Modbus, HTTP, how a command acts (the scan process does).

asyncua gives a method callback no session and stores a client's write in the address space;
both are wrong here (methods need the caller's identity; a written symbol takes its value from
the next scan, not from the client), so each session's `write` and `call` are wrapped at
session creation (`_hook_sessions`): ours are answered here, others go to asyncua (whose
write answers BadUserAccessDenied for a node that does not exist: BadNodeIdUnknown here).
Read and Republish are answered per session by sessions.py. The server names itself softplc
(ApplicationUri, ProductUri, BuildInfo with the package's version), not FreeOpcUa.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import math
from collections.abc import Callable
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any, Final, Protocol

from asyncua import ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_session import InternalSession

import softplc
from softplc.core.image import split_registers
from softplc.core.present import NOT_FINITE
from softplc.core.snapshot import (
    ChannelFull,
    HmiWrite,
    SnapshotSource,
    SnapshotUnavailable,
)
from softplc.opcua.access import METHOD_ACTS, decide, who
from softplc.opcua.door import DoorServer
from softplc.opcua.ids import numeric_id, status_code, string_id
from softplc.opcua.limits import DoorStats, OpcUaLimits
from softplc.opcua.mirror import Mirror
from softplc.opcua.program import CommandChannel, Outcome, ProgramHandling, arguments, misnamed
from softplc.opcua.secure import Security, application_uri
from softplc.opcua.sessions import hook
from softplc.opcua.space import METHODS, NAMESPACE_URI, PROGRAM, Space, SymbolNode
from softplc.opcua.typed import Refusal
from softplc.security.roles import Act

log = logging.getLogger(__name__)

DEFAULT_PORT: Final = 4840
POLL_S: Final = 0.02  # snapshot: 50 looks a second, each pushing only what changed
BOARD_POLL_S: Final = 0.1  # board (JSON, refreshed ~every 50 ms by the scan): marking, events


class BoardSource(Protocol):
    def read(self) -> dict[str, Any]: ...


class OpcUaServer:
    """One server on `host:port` (port 0: a free port, see `bound_port`)."""

    def __init__(self, channel: CommandChannel, snapshots: SnapshotSource, board: BoardSource,
                 *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, state_dir: Path,
                 modbus_writes: str = "open", poll_s: float = POLL_S,
                 board_poll_s: float = BOARD_POLL_S, limits: OpcUaLimits | None = None) -> None:
        self.host, self.port = host, port
        self.limits = limits or OpcUaLimits()
        self.state_dir = Path(state_dir)
        self.modbus_writes = modbus_writes
        self.poll_s, self.board_poll_s = poll_s, board_poll_s
        self._channel = channel
        self._snapshots = snapshots
        self._board = board
        self._server: DoorServer | None = None
        self.space: Space | None = None
        self.security = Security(self.state_dir, host, port)
        self._handling = ProgramHandling(channel, self._after_command, self.security.programs)
        self._methods: dict[ua.NodeId, str] = {}
        self._mirror: Mirror | None = None  # the address space kept in step, once started
        self._task: asyncio.Task[None] | None = None

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://{self.host}:{self.bound_port}"

    @property
    def bound_port(self) -> int:
        server = self._server
        if server is None or server.bserver is None or server.bserver._server is None:
            raise RuntimeError("the OPC UA server is not started")
        bound = server.bserver._server
        if not isinstance(bound, asyncio.Server):
            raise RuntimeError("the OPC UA server has no listening socket")
        port: int = bound.sockets[0].getsockname()[1]
        return port

    @property
    def door_stats(self) -> DoorStats:
        """What the door admitted, evicted and refused since start (docs/opcua.md)."""
        door = self._server.door if self._server is not None else None
        return door.stats if door is not None else DoorStats()

    async def start(self) -> None:
        _quiet_asyncua()
        await self.security.prepare()
        server = self.security.server(self.limits)
        await server.init()
        server.set_endpoint(f"opc.tcp://{self.host}:{self.port}")
        await _identify(server, self.port)
        await self.security.apply(server)
        ns = await server.register_namespace(NAMESPACE_URI)
        self._server, self.space = server, Space(server, ns)
        self._handling.space = self.space  # Part 10 checks of calls (part10.py)
        await self.space.build_static()
        await self._add_methods(ns)
        events = await self._event_generator(server, ns)
        self._mirror = Mirror(server, self.space, events, self.modbus_writes)
        self._hook_sessions(server)
        await self._first_look(self._mirror)
        await server.start()
        self._task = asyncio.create_task(self._poll(), name="softplc-opcua-poll")
        log.info("OPC UA on %s (security None and anonymous read %s)", self.endpoint,
                 "on" if self.security.loopback else "off")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._server is not None:
            await _end_clock(self._server)
            with contextlib.suppress(Exception):  # a half-started server still releases its port
                await self._server.stop()
            self._server = None
        await self.security.stop()

    # -- setup ------------------------------------------------------------------------------

    async def _add_methods(self, ns: int) -> None:
        """Start..Reset are the Part 10 type's own methods (instantiated with the Program
        object, browse names in namespace 0); Download is ours."""
        assert self.space is not None and self.space.program is not None
        for name in METHODS:
            nodeid = string_id(f"{PROGRAM}.{name}", ns)
            if name == "Download":
                inputs, outputs = arguments(name)
                await self.space.program.add_method(nodeid, f"{ns}:{name}", _unguarded,
                                                    inputs, outputs)
            self._methods[nodeid] = name

    async def _event_generator(self, server: DoorServer, ns: int) -> Any:
        assert self.space is not None and self.space.plc is not None
        etype = await server.create_custom_event_type(
            ns, "SoftplcEventType", ua.ObjectIds.BaseEventType,
            [("EventName", ua.VariantType.String), ("Seq", ua.VariantType.UInt32),
             ("Scan", ua.VariantType.UInt64)])
        return await server.get_event_generator(etype, self.space.plc.nodeid)

    def _hook_sessions(self, server: DoorServer) -> None:
        iserver = server.iserver
        create = iserver.create_session

        def create_session(name: str, user: User | None = None,
                           external: bool = False) -> InternalSession:
            session = create(name, user or User(role=UserRole.Anonymous), external)
            if external:  # the server's own session keeps asyncua's behaviour
                session.write = partial(self._write, session, session.write)  # type: ignore
                session.call = partial(self._call, session, session.call)  # type: ignore
                hook(session, self._methods.get)  # Read per role, Republish as the spec says
            return session

        iserver.create_session = create_session  # type: ignore[method-assign]

    async def _first_look(self, mirror: Mirror) -> None:
        document = await self._read_board()
        snapshot = None
        with contextlib.suppress(SnapshotUnavailable):
            snapshot = self._snapshots.latest()
        await mirror.first_look(document, snapshot)

    # -- services ---------------------------------------------------------------------------

    async def _write(self, session: InternalSession, inner: Callable[..., Any],
                     params: ua.WriteParameters) -> list[ua.StatusCode]:
        results: list[ua.StatusCode | None] = []
        others: list[ua.WriteValue] = []
        written: dict[str, tuple[object, int]] = {}  # symbol -> (value, status): audited
        for value in params.NodesToWrite:
            symbol = self._mirror.by_node.get(value.NodeId) if self._mirror else None
            if symbol is None and value.NodeId not in session.iserver.aspace:
                results.append(status_code(ua.StatusCodes.BadNodeIdUnknown))
            elif symbol is None:
                others.append(value)
                results.append(None)
            else:
                code = self._write_symbol(session, symbol, value)
                written[symbol.name] = (_plain(value), code)
                results.append(status_code(code))
        if written:
            await self._audit_writes(session, written)
        if others:
            passed = iter(await inner(ua.WriteParameters(NodesToWrite=others)))
            results = [r if r is not None else next(passed) for r in results]
        return [r for r in results if r is not None]

    async def _audit_writes(self, session: InternalSession,
                            written: dict[str, tuple[object, int]]) -> None:
        """One record per Write request (a request of 1,000 symbols is one fsync, not
        1,000; the trail keeps the first 32 of them)."""
        refused = {name: code for name, (_, code) in written.items()
                   if code != ua.StatusCodes.Good}
        outcome = "queued" if not refused else "partly" if len(refused) < len(written) \
            else "denied" if ua.StatusCodes.BadUserAccessDenied in refused.values() \
            else "refused"
        detail: dict[str, object] = {"values": {n: v for n, (v, _) in written.items()}}
        if refused:
            detail["refused"] = {n: status_code(c).name for n, c in refused.items()}
        await self.security.recorder.record(
            who(session), "write", outcome, next(iter(refused.values()), ua.StatusCodes.Good),
            detail)

    def _write_symbol(self, session: InternalSession, symbol: SymbolNode,
                      value: ua.WriteValue) -> int:
        if value.AttributeId != ua.AttributeIds.Value:
            return ua.StatusCodes.BadNotWritable
        if not decide(session, Act.WRITE).allowed:
            return ua.StatusCodes.BadUserAccessDenied  # anonymous and viewers: read only
        if not symbol.writable:
            return ua.StatusCodes.BadNotWritable  # an input, or the write policy says no
        with contextlib.suppress(SnapshotUnavailable):
            if self._snapshots.latest().status.program_hash != self._built_hash():
                return ua.StatusCodes.BadInvalidState  # a download is being rebuilt: browse again
        raw = symbol.written(value.Value.Value if value.Value is not None else None)
        if isinstance(raw, Refusal):
            log.info("OPC UA write to %s refused: %s", symbol.name, raw.text)
            return raw.code
        location = symbol.location
        if location is None:
            return ua.StatusCodes.BadNodeIdUnknown
        # a double or long word goes whole, as its 2 or 4 registers (one HMI write)
        registers = (raw,) if location.is_bit else tuple(split_registers(raw, location.width))
        try:
            self._channel.send_hmi_write(HmiWrite(location, registers))
        except ChannelFull:
            return ua.StatusCodes.BadResourceUnavailable
        return ua.StatusCodes.Good

    async def _call(self, session: InternalSession, inner: Callable[..., Any],
                    params: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        results: list[ua.CallMethodResult] = []
        for request in params:
            method = self._handling.method_of(request)  # type's ids too (issue 29)
            if (refused := misnamed(request, session.iserver.aspace)) or method is None:
                results.extend([refused] if refused else await inner([request]))  # Part 4
                continue
            decision = decide(session, METHOD_ACTS[method])
            if not decision.allowed:
                held = decision.role.label if decision.role else "none"
                why = f"; {decision.why_none}" if decision.why_none else ""
                result = Outcome(ua.StatusCodes.BadUserAccessDenied,
                                 f"{method} needs the {decision.need.label} role (this "
                                 f"session: {held}{why})").result()
            else:
                result = await self._handling.call(method, request.InputArguments or [],
                                                   request.ObjectId)
            await self._audit_call(session, method, request, result)
            results.append(result)
        return results

    async def _audit_call(self, session: InternalSession, method: str,
                          request: ua.CallMethodRequest, result: ua.CallMethodResult) -> None:
        code = result.StatusCode.value
        outcome = "applied" if code == ua.StatusCodes.Good else "denied" if \
            code == ua.StatusCodes.BadUserAccessDenied else "refused"
        outputs = result.OutputArguments or []
        detail: dict[str, object] = {"message": outputs[0].Value if outputs else ""}
        args = [a.Value for a in request.InputArguments or []]
        if method == "Download" and args and isinstance(args[0], str):
            body = args[0].encode()
            detail.update(sha256=hashlib.sha256(body).hexdigest(), bytes=len(body),
                          online=args[1] if len(args) > 1 else None,
                          name=args[2] if len(args) > 2 else None)
        await self.security.recorder.record(who(session), method, outcome, code, detail)

    async def _after_command(self, method: str, outcome: Outcome) -> None:
        assert self._mirror is not None
        await self._mirror.command_done(method, outcome)

    def _built_hash(self) -> str | None:
        return None if self._mirror is None else self._mirror.built_hash

    # -- polling ----------------------------------------------------------------------------

    async def _poll(self) -> None:
        assert self._mirror is not None
        mirror = self._mirror
        loop = asyncio.get_running_loop()
        next_board = loop.time()
        while True:
            try:
                document = None
                if loop.time() >= next_board:
                    next_board = loop.time() + self.board_poll_s
                    document = await self._read_board()
                    await mirror.board_values(document)
                await self._snapshot_values(mirror, document)
            except asyncio.CancelledError:
                raise
            except Exception:  # a bad poll must not end the service: log, try again
                log.exception("OPC UA poll failed")
            await asyncio.sleep(self.poll_s)

    async def _read_board(self) -> dict[str, Any]:
        try:
            return await asyncio.to_thread(self._board.read)
        except (TimeoutError, ValueError):
            return {}

    async def _snapshot_values(self, mirror: Mirror, document: dict[str, Any] | None) -> None:
        try:
            snapshot = self._snapshots.latest()
        except SnapshotUnavailable:
            await mirror.lost()
            return
        status = snapshot.status
        if status.program_hash != mirror.built_hash:
            await mirror.maybe_rebuild(status.program_hash, document or await self._read_board())
        await mirror.transitions(snapshot)
        await mirror.push(snapshot)


async def _end_clock(server: DoorServer) -> None:
    """Cancel asyncua's once-a-second clock task (ServerStatus.CurrentTime): its own stop
    sets a flag and waits for the task to see it, up to 1 s (measured 0.9 s of a SIGTERM's
    2 s)."""
    iserver = server.iserver
    task, iserver.time_task = iserver.time_task, None
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def _identify(server: DoorServer, port: int) -> None:
    """softplc's own ApplicationUri (per host and port: several softplcs may share a host),
    ProductUri and BuildInfo (the package's version; BuildDate: when the package's
    __init__.py was written, i.e. installed or checked out)."""
    server.set_server_name("softplc")
    server.product_uri = NAMESPACE_URI
    server.manufacturer_name = "softplc"
    uri = application_uri(port)
    await server.set_application_uri(uri)  # NamespaceArray[1]; ServerArray[0] too (Part 5)
    await server.get_node(numeric_id(ua.ObjectIds.Server_ServerArray)).write_value(
        ua.Variant([uri], ua.VariantType.String))
    built = datetime.fromtimestamp(Path(softplc.__file__).stat().st_mtime, UTC)
    await server.set_build_info(NAMESPACE_URI, "softplc", "softplc", softplc.__version__,
                                softplc.__version__, built)


def _quiet_asyncua() -> None:
    """asyncua logs a traceback at ERROR for every malformed message and INFO for every
    request: a peer could flood the log (and block a process whose stderr is a full pipe).
    Our own logger reports what matters. An explicitly set level is kept."""
    logger = logging.getLogger("asyncua")
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.CRITICAL)


def _plain(value: ua.WriteValue) -> object:
    """The written value as the audit trail keeps it (JSON: a number, a bool or text)."""
    variant = value.Value.Value if value.Value is not None else None
    plain = variant.Value if variant is not None else None
    if isinstance(plain, float) and not math.isfinite(plain):
        return NOT_FINITE[repr(plain)]  # JSON has no NaN: the text the API shows
    return plain if isinstance(plain, int | float | str | None) else repr(plain)


async def _unguarded(parent: ua.NodeId, *args: ua.Variant) -> ua.StatusCode:
    """Reached only by asyncua's own session (sessions of clients are hooked)."""
    return status_code(ua.StatusCodes.BadUserAccessDenied)
