"""The OPC UA server of the communication process (asyncua), beside Modbus and the HTTP API.

Owns: starting/stopping asyncua on one endpoint, who may do what (anonymous sessions read on
a loopback bind; writes and method calls need the user token whose password is the API token
of STATE_DIR), symbol writes (checked against the Modbus write policy and the symbol's type,
then journaled through the channel like Modbus and API writes, never stored in the address
space), polling the snapshot (every `poll_s`) and the status board (every `board_poll_s`) and
pushing only changed values, rebuilding the program's nodes when a download changes the
program hash, and turning board events, downloads, state changes and faults into OPC UA events.
Does not know: the scan, Modbus, HTTP, how a command acts (the scan process does).

asyncua gives a method callback no session and stores a client's write in the address space;
both are wrong here (methods need the caller's identity; a written symbol takes its value from
the next scan, not from the client), so each session's `write` and `call` are wrapped at
session creation (`_hook_sessions`): ours are answered here, others go to asyncua.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
from collections.abc import Callable, Mapping
from functools import partial
from pathlib import Path
from typing import Any, Final, Protocol

from asyncua import Server, ua
from asyncua.crypto.permission_rules import (
    USER_TYPES,
    SimpleRoleRuleset,
    User,
    UserRole,
)
from asyncua.server.internal_session import InternalSession
from asyncua.server.user_managers import UserManager

from softplc.api import auth
from softplc.core.image import AddressError
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import (
    ChannelFull,
    HmiWrite,
    Snapshot,
    SnapshotSource,
    SnapshotUnavailable,
)
from softplc.opcua.ids import numeric_id, status_code, string_id
from softplc.opcua.program import CommandChannel, Outcome, ProgramHandling, arguments
from softplc.opcua.space import (
    METHODS,
    NAMESPACE_URI,
    PROGRAM,
    PartState,
    Space,
    SymbolNode,
    part10_state,
)

log = logging.getLogger(__name__)

DEFAULT_PORT: Final = 4840
POLL_S: Final = 0.02  # snapshot: 50 looks a second, each pushing only what changed
BOARD_POLL_S: Final = 0.1  # board (JSON, refreshed ~every 50 ms by the scan): marking, events
OPERATOR: Final = "operator"  # the documented user name; any name works, the password counts


class BoardSource(Protocol):
    def read(self) -> dict[str, Any]: ...


class TokenUsers(UserManager):
    """asyncua UserManager: a user name with the API token as password is an operator
    (read, write, call); no identity is anonymous (read only), and only on a loopback bind."""

    def __init__(self, token: str, anonymous: bool) -> None:
        self._token = token
        self._anonymous = anonymous

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if not username and password is None:  # anonymous (a certificate alone is no user)
            return User(role=UserRole.Anonymous) if self._anonymous else None
        if password is not None and hmac.compare_digest(str(password).encode(),
                                                        self._token.encode()):
            return User(role=UserRole.User, name=username or OPERATOR)
        return None  # wrong token: BadUserAccessDenied at ActivateSession


class ClientServices(SimpleRoleRuleset):
    """Which services a session may request at all: every client service, anonymous or not
    (a write or call of an anonymous session is refused per item, with a status code, by
    the session hooks); changing the address space (AddNodes etc.) for nobody."""

    def __init__(self) -> None:
        # SimpleRoleRuleset's own tables are not used: check_validity is the whole rule.
        self._allowed = frozenset(numeric_id(i) for i in USER_TYPES)

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        return user.role is not UserRole.Admin and action_type_id in self._allowed


def _may_act(session: InternalSession) -> bool:
    user = session.user
    return user is not None and user.role in (UserRole.User, UserRole.Admin)


class OpcUaServer:
    """One server on `host:port` (port 0: a free port, see `bound_port`)."""

    def __init__(self, channel: CommandChannel, snapshots: SnapshotSource, board: BoardSource,
                 *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, state_dir: Path,
                 modbus_writes: str = "open", poll_s: float = POLL_S,
                 board_poll_s: float = BOARD_POLL_S) -> None:
        self.host, self.port = host, port
        self.state_dir = Path(state_dir)
        self.modbus_writes = modbus_writes
        self.poll_s, self.board_poll_s = poll_s, board_poll_s
        self._channel = channel
        self._snapshots = snapshots
        self._board = board
        self._server: Server | None = None
        self.space: Space | None = None
        self._handling = ProgramHandling(channel, self._after_command)
        self._methods: dict[ua.NodeId, str] = {}
        self._by_node: dict[ua.NodeId, SymbolNode] = {}
        self._built_hash: str | None = None
        self._values: dict[Any, Any] = {}  # node id -> last value pushed
        self._part10: PartState | None = None
        self._state: PlcState | None = None
        self._fault = 0
        self._event_seq = 0
        self._events: Any = None
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

    async def start(self) -> None:
        _quiet_asyncua()
        token = await asyncio.to_thread(auth.load_or_create_token, self.state_dir)
        server = Server(user_manager=TokenUsers(token, auth.is_loopback(self.host)))
        await server.init()
        server.set_endpoint(f"opc.tcp://{self.host}:{self.port}")
        server.set_server_name("softplc")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity], ClientServices())
        server.set_identity_tokens([ua.AnonymousIdentityToken, ua.UserNameIdentityToken])
        ns = await server.register_namespace(NAMESPACE_URI)
        self._server, self.space = server, Space(server, ns)
        await self.space.build_static()
        await self._add_methods(ns)
        self._events = await self._event_generator(server, ns)
        self._hook_sessions(server)
        await self._first_look()
        await server.start()
        self._task = asyncio.create_task(self._poll(), name="softplc-opcua-poll")
        log.info("OPC UA on %s (anonymous read %s)", self.endpoint,
                 "on" if auth.is_loopback(self.host) else "off")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        if self._server is not None:
            with contextlib.suppress(Exception):  # a half-started server still releases its port
                await self._server.stop()
            self._server = None

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

    async def _event_generator(self, server: Server, ns: int) -> Any:
        assert self.space is not None and self.space.plc is not None
        etype = await server.create_custom_event_type(
            ns, "SoftplcEventType", ua.ObjectIds.BaseEventType,
            [("EventName", ua.VariantType.String), ("Seq", ua.VariantType.UInt32),
             ("Scan", ua.VariantType.UInt64)])
        return await server.get_event_generator(etype, self.space.plc.nodeid)

    def _hook_sessions(self, server: Server) -> None:
        iserver = server.iserver
        create = iserver.create_session

        def create_session(name: str, user: User | None = None,
                           external: bool = False) -> InternalSession:
            session = create(name, user or User(role=UserRole.Anonymous), external)
            if external:  # the server's own session keeps asyncua's behaviour
                session.write = partial(self._write, session, session.write)  # type: ignore
                session.call = partial(self._call, session, session.call)  # type: ignore
            return session

        iserver.create_session = create_session  # type: ignore[method-assign]

    async def _first_look(self) -> None:
        """Nodes of the program that runs now; events from now on (no replay of old ones)."""
        document = await self._read_board()
        self._event_seq = _newest_seq(document)
        with contextlib.suppress(SnapshotUnavailable):
            snapshot = self._snapshots.latest()
            self._state = snapshot.status.state
            self._part10 = part10_state(snapshot.status.state, None)
            await self._maybe_rebuild(snapshot.status.program_hash, document)
            await self._push(snapshot)
        if self._part10 is not None and self.space is not None:
            await self.space.set_part10_state(self._part10)

    # -- services ---------------------------------------------------------------------------

    async def _write(self, session: InternalSession, inner: Callable[..., Any],
                     params: ua.WriteParameters) -> list[ua.StatusCode]:
        results: list[ua.StatusCode | None] = []
        others: list[ua.WriteValue] = []
        for value in params.NodesToWrite:
            symbol = self._by_node.get(value.NodeId)
            if symbol is None:
                others.append(value)
                results.append(None)
            else:
                results.append(status_code(self._write_symbol(session, symbol, value)))
        if others:
            passed = iter(await inner(ua.WriteParameters(NodesToWrite=others)))
            results = [r if r is not None else next(passed) for r in results]
        return [r for r in results if r is not None]

    def _write_symbol(self, session: InternalSession, symbol: SymbolNode,
                      value: ua.WriteValue) -> int:
        if value.AttributeId != ua.AttributeIds.Value:
            return ua.StatusCodes.BadNotWritable
        if not _may_act(session):
            return ua.StatusCodes.BadUserAccessDenied  # anonymous: read only
        if not symbol.writable:
            return ua.StatusCodes.BadNotWritable  # an input, or the write policy says no
        with contextlib.suppress(SnapshotUnavailable):
            if self._snapshots.latest().status.program_hash != self._built_hash:
                return ua.StatusCodes.BadInvalidState  # a download is being rebuilt: browse again
        variant = value.Value.Value if value.Value is not None else None
        number = _written_value(symbol, variant.Value if variant is not None else None)
        if isinstance(number, str):
            log.info("OPC UA write to %s refused: %s", symbol.name, number)
            return ua.StatusCodes.BadTypeMismatch
        if symbol.location is None:
            return ua.StatusCodes.BadNodeIdUnknown
        try:
            self._channel.send_hmi_write(HmiWrite(symbol.location, (number,)))
        except ChannelFull:
            return ua.StatusCodes.BadResourceUnavailable
        return ua.StatusCodes.Good

    async def _call(self, session: InternalSession, inner: Callable[..., Any],
                    params: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        results: list[ua.CallMethodResult] = []
        for request in params:
            method = self._methods.get(request.MethodId)
            if method is None:
                results.extend(await inner([request]))
            elif not _may_act(session):
                results.append(Outcome(ua.StatusCodes.BadUserAccessDenied,
                                       f"{method} needs the operator's user token "
                                       "(password: the API token in STATE_DIR/api_token)").result())
            else:
                results.append(await self._handling.call(method, request.InputArguments or []))
        return results

    async def _after_command(self, method: str, outcome: Outcome) -> None:
        assert self.space is not None
        text = outcome.message if outcome.ok else f"{method} refused: {outcome.message}"
        await self._set(self.space.status["LastResult"].nodeid,
                        ua.Variant(text, ua.VariantType.String))
        await self._set(self.space.status["LastProblems"].nodeid,
                        ua.Variant(list(outcome.problems), ua.VariantType.String))
        if not outcome.ok:
            await self._emit("refused", text + "".join(f"\n{p}" for p in outcome.problems))

    # -- polling ----------------------------------------------------------------------------

    async def _poll(self) -> None:
        loop = asyncio.get_running_loop()
        next_board = loop.time()
        while True:
            try:
                document = None
                if loop.time() >= next_board:
                    next_board = loop.time() + self.board_poll_s
                    document = await self._read_board()
                    await self._board_values(document)
                await self._snapshot_values(document)
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

    async def _snapshot_values(self, document: dict[str, Any] | None) -> None:
        try:
            snapshot = self._snapshots.latest()
        except SnapshotUnavailable:
            return
        status = snapshot.status
        if status.program_hash != self._built_hash:
            await self._maybe_rebuild(status.program_hash, document or await self._read_board())
        await self._transitions(snapshot)
        await self._push(snapshot)

    async def _maybe_rebuild(self, program_hash: str, document: Mapping[str, Any]) -> None:
        if (document.get("program_hash") or "") != program_hash:
            return  # the board does not describe this program yet: next board poll
        assert self.space is not None
        await self.space.build_program(document, self.modbus_writes)
        self._by_node = {s.node.nodeid: s for s in self.space.symbols.values()}
        self._values = {}
        previous, self._built_hash = self._built_hash, program_hash
        if previous is not None and program_hash:
            await self._emit("download", f"program {document.get('program')} loaded "
                             f"(sha256 {program_hash[:12]}), state {document.get('state')}")
            self._part10 = PartState.RUNNING if self._state is PlcState.RUNNING \
                else PartState.READY
            await self.space.set_part10_state(self._part10)

    async def _transitions(self, snapshot: Snapshot) -> None:
        status = snapshot.status
        if status.state is not self._state:
            before, self._state = self._state, status.state
            self._part10 = part10_state(status.state, self._part10)
            assert self.space is not None
            await self.space.set_part10_state(self._part10)
            await self._emit("state", f"{before.name if before else '?'} -> {status.state.name}"
                             f" (Part 10: {self._part10.text})", scan=status.scan_count)
        if status.fault_code != self._fault:
            self._fault = status.fault_code
            if status.fault_code:
                await self._emit("fault", f"fault code {status.fault_code}",
                                 scan=status.scan_count, severity=900)

    async def _push(self, snapshot: Snapshot) -> None:
        image, status = snapshot.image, snapshot.status
        for symbol in self._by_node.values():
            if symbol.location is not None:
                with contextlib.suppress(AddressError, IndexError):
                    await self._set(symbol.node.nodeid, symbol.variant(image.get(symbol.location)))
        assert self.space is not None
        nodes = self.space.status
        for name, value in (("State", status.state.name), ("ProgramHash", status.program_hash),
                            ("ScanCount", status.scan_count), ("PeriodUs", status.period_us),
                            ("LastExecUs", status.last_exec_us),
                            ("MaxExecUs", status.max_exec_us),
                            ("P99LatenessUs", status.p99_lateness_us),
                            ("Overruns", status.overruns), ("FaultCode", status.fault_code)):
            await self._set(nodes[name].nodeid, _status_variant(name, value))

    async def _board_values(self, document: dict[str, Any]) -> None:
        if not document or self.space is None:
            return
        nodes = self.space.status
        await self._set(nodes["Program"].nodeid, _status_variant("Program",
                                                                 document.get("program") or ""))
        await self._set(nodes["FaultReason"].nodeid,
                        _status_variant("FaultReason", document.get("fault_reason") or ""))
        restarts = document.get("restarts")
        if isinstance(restarts, int):
            await self._set(nodes["Restarts"].nodeid, _status_variant("Restarts", restarts))
        if document.get("program_hash") == self._built_hash:
            marking = document.get("marking") or {}
            for place in marking:
                await self.space.place(str(place))
            for place, node in self.space.places.items():  # unmarked places are absent: 0
                count = marking.get(place, 0)
                await self._set(node.nodeid, ua.Variant(count if isinstance(count, int) else 0,
                                                        ua.VariantType.UInt32))
        await self._board_events(document)

    async def _board_events(self, document: dict[str, Any]) -> None:
        events = [e for e in document.get("events") or []
                  if isinstance(e, dict) and isinstance(e.get("seq"), int)]
        newest = _newest_seq(document)
        if newest < self._event_seq:  # the scan process restarted: its seq starts again
            self._event_seq = 0
        for event in events:
            if event["seq"] > self._event_seq:
                name = str(event.get("name"))
                await self._emit(name, f"event {name}", seq=event["seq"],
                                 scan=int(event.get("scan") or 0))
        self._event_seq = max(self._event_seq, newest)
        assert self.space is not None
        await self._set(self.space.status["LastEventSeq"].nodeid,
                        ua.Variant(self._event_seq & 0xFFFFFFFF, ua.VariantType.UInt32))

    async def _set(self, nodeid: ua.NodeId, variant: ua.Variant) -> None:
        """Write a value into the address space only when it changed (subscribers are told
        of changes only; an unchanged write would still cost a comparison per item)."""
        if self._values.get(nodeid) == variant.Value:
            return
        self._values[nodeid] = variant.Value
        assert self._server is not None
        await self._server.write_attribute_value(nodeid, ua.DataValue(variant))

    async def _emit(self, name: str, message: str, *, seq: int = 0, scan: int = 0,
                    severity: int = 500) -> None:
        event = self._events.event
        event.EventName, event.Seq, event.Scan = name, seq & 0xFFFFFFFF, scan
        event.Severity = severity
        await self._events.trigger(message=message)


def _quiet_asyncua() -> None:
    """asyncua logs a traceback at ERROR for every malformed message and INFO for every
    request: a peer could flood the log (and block a process whose stderr is a full pipe).
    Our own logger reports what matters. An explicitly set level is kept."""
    logger = logging.getLogger("asyncua")
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.CRITICAL)


async def _unguarded(parent: ua.NodeId, *args: ua.Variant) -> ua.StatusCode:
    """Reached only by asyncua's own session (sessions of clients are hooked)."""
    return status_code(ua.StatusCodes.BadUserAccessDenied)


def _newest_seq(document: Mapping[str, Any]) -> int:
    return max((int(e["seq"]) for e in document.get("events") or []
                if isinstance(e, dict) and isinstance(e.get("seq"), int)), default=0)


def _written_value(symbol: SymbolNode, value: object) -> int | str:
    """The image value of a client's write, or why it does not fit the symbol's type."""
    if symbol.is_bool:
        if isinstance(value, bool):
            return int(value)
        return f"{symbol.name} is Boolean, got {type(value).__name__}"
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 0xFFFF:
        return value
    return f"{symbol.name} is UInt16 (0..65535), got {value!r}"


_STATUS_TYPES: Final = {"State": ua.VariantType.String, "ProgramHash": ua.VariantType.String,
                        "Program": ua.VariantType.String, "FaultReason": ua.VariantType.String,
                        "ScanCount": ua.VariantType.UInt64, "FaultCode": ua.VariantType.UInt16}


def _status_variant(name: str, value: object) -> ua.Variant:
    vtype = _STATUS_TYPES.get(name, ua.VariantType.UInt32)
    if vtype is ua.VariantType.String:
        return ua.Variant(str(value), vtype)
    return ua.Variant(int(value) if isinstance(value, int) else 0, vtype)
