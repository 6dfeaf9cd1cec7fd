"""The OPC UA server's door: who gets a connection, how much a peer may send, and how many
sessions, subscriptions, monitored items and operations per request it may ask for.

Owns: asyncua's Server with our BinaryServer (`DoorServer`), the connection rule (the
Modbus slave's, hmi/admission.py: admit, else evict a connection that never activated a
session or is idle longest, else refuse), closing a connection that announces a chunk
larger than the negotiated buffer (before it is buffered), refusing a request with too many
operations before its body is decoded (limits.operations), one session per connection and
at most `max_sessions` (sessions left by their connection go first), the subscription and
monitored-item caps and the publishing-interval floor, refusing an OpenSecureChannel whose
certificate `channel_check` refuses (before anything is decrypted: an Error message, then
close), passing each request through `guard` (server.py: logins), and the counts of all
refusals: logged as one summary line at most every SUMMARY_S, never one line per refusal.
Does not know: symbols, the channel, the PLC, users, which certificates are trusted.

asyncua 2.1 keeps its door in OPCUAProtocol/BinaryServer/UaProcessor with no hooks for
these rules, so the connection class is a subclass and the processor's dispatch and the
subscription service are wrapped per instance; tests/opcua/test_limits.py holds each rule
to a hostile client, so an asyncua upgrade that moves them fails there first.
"""

from __future__ import annotations

import asyncio
import logging
import math
import resource
import struct
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from functools import partial
from typing import Any, Final

from asyncua import Server, ua
from asyncua.common.connection import TransportLimits
from asyncua.common.utils import Buffer, ServiceError
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.internal_server import InternalServer
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary, uatcp_to_binary

from softplc.hmi.admission import Limits, Slot, Verdict, decide
from softplc.opcua.ids import numeric_id, status_code
from softplc.opcua.limits import DoorStats, OpcUaLimits, operations

log = logging.getLogger(__name__)

SUMMARY_S: Final = 10.0  # at most one summary line of refusals per this
FD_RESERVE: Final = 64  # descriptors kept for the listener, the channel, shm, logs
# Requests a connection may make before its session is activated: a client needs Hello,
# OpenSecureChannel, GetEndpoints, CreateSession and ActivateSession, and a few retries. A
# connection that keeps asking without activating is closed however quickly it asks.
MAX_UNACTIVATED_REQUESTS: Final = 16
_HEADER: Final = struct.Struct("<3scI")  # message type, chunk type, message size
_CREATE_SESSION: Final = numeric_id(ua.ObjectIds.CreateSessionRequest_Encoding_DefaultBinary)
# (peer, SecurityPolicyUri, the sender's certificate) -> a refusal's status code, or None
ChannelCheck = Callable[[str, str, bytes | None], int | None]
# (peer, processor, typeid, requesthdr, body, the request's dispatch) -> its answer
Guard = Callable[[str, UaProcessor, ua.NodeId, Any, Buffer, Callable[[], Awaitable[Any]]],
                 Awaitable[Any]]


def usable_connections(limits: OpcUaLimits) -> int:
    """`max_connections`, lowered to what the process's descriptor limit really allows: a
    door that accepts past RLIMIT_NOFILE makes accept() fail in a loop."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return limits.max_connections
    return max(1, min(limits.max_connections, soft - FD_RESERVE))


class DoorServer(Server):
    """asyncua's Server whose transport is our `Door` and whose limits are `limits`."""

    def __init__(self, limits: OpcUaLimits, channel_check: ChannelCheck | None = None,
                 guard: Guard | None = None, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.door_limits = limits
        self.channel_check, self.guard = channel_check, guard
        self.limits = TransportLimits(
            max_recv_buffer=limits.chunk_bytes, max_send_buffer=limits.chunk_bytes,
            max_chunk_count=limits.max_chunk_count, max_message_size=limits.max_message_bytes)
        _bound_iserver(self.iserver, limits)
        self.door: Door | None = None

    async def start(self) -> None:
        """As Server.start (asyncua 2.1, no certificates), with our BinaryServer."""
        await self._setup_server_nodes()
        await self.iserver.start()
        host, port = self._get_bind_socket_info()
        door = Door(self.iserver, host, port, self.limits, self.door_limits)
        door.channel_check, door.guard = self.channel_check, self.guard
        self.bserver = self.door = door
        door.set_policies(self._policies)
        try:
            await door.start()
        except Exception:
            await self.iserver.stop()
            raise
        await self._publish_operation_limits()

    async def _publish_operation_limits(self) -> None:
        """Part 5's OperationLimits, so that a client can split its requests to fit."""
        limits = self.door_limits
        for name, value in (("MaxNodesPerRead", limits.max_nodes_per_read),
                            ("MaxNodesPerWrite", limits.max_nodes_per_write),
                            ("MaxNodesPerBrowse", limits.max_nodes_per_browse),
                            ("MaxNodesPerMethodCall", limits.max_methods_per_call),
                            ("MaxMonitoredItemsPerCall", limits.max_monitored_items_per_call),
                            ("MaxNodesPerRegisterNodes", limits.max_nodes_per_other),
                            ("MaxNodesPerTranslateBrowsePathsToNodeIds",
                             limits.max_nodes_per_other)):
            ident = getattr(ua.ObjectIds, f"Server_ServerCapabilities_OperationLimits_{name}")
            await self.get_node(numeric_id(ident)).write_value(
                ua.Variant(value, ua.VariantType.UInt32))


def _bound_iserver(iserver: InternalServer, limits: OpcUaLimits) -> None:
    # Our door decides first; asyncua's own cap stays as a backstop above ours (closing
    # connections stay in its list until their connection_lost runs).
    iserver.max_connections = 4 * limits.max_connections
    iserver.max_pending_activation_seconds = limits.activation_timeout_s
    iserver.max_pending_messages_per_connection = limits.max_queued_chunks
    iserver.max_session_timeout_ms = limits.max_session_timeout_s * 1000
    iserver.min_session_timeout_ms = min(iserver.min_session_timeout_ms,
                                         iserver.max_session_timeout_ms)
    iserver.max_subscriptions = limits.max_subscriptions
    iserver.max_monitored_item_queue_size = 100  # values queued per item between publishes
    iserver.max_unacked_messages_per_subscription = 100
    service = iserver.subscription_service
    service.create_subscription = partial(  # type: ignore[method-assign]
        _create_subscription, service, service.create_subscription, limits)
    service.create_monitored_items = partial(  # type: ignore[method-assign]
        _create_monitored_items, service, service.create_monitored_items, limits)


async def _create_subscription(service: Any, inner: Callable[..., Any], limits: OpcUaLimits,
                               params: ua.CreateSubscriptionParameters, callback: Any,
                               session_id: ua.NodeId, **kwargs: Any) -> Any:
    own = sum(1 for sub in service.subscriptions.values() if sub.session_id == session_id)
    if own >= limits.max_subscriptions_per_session:
        raise ServiceError(ua.StatusCodes.BadTooManySubscriptions)
    requested = params.RequestedPublishingInterval
    if not (math.isfinite(requested) and requested >= limits.min_publishing_interval_ms):
        params.RequestedPublishingInterval = limits.min_publishing_interval_ms
    return await inner(params, callback, session_id, **kwargs)


async def _create_monitored_items(service: Any, inner: Callable[..., Any],
                                  limits: OpcUaLimits,
                                  params: ua.CreateMonitoredItemsParameters) -> Any:
    """The items that fit under `max_monitored_items`; the others get
    BadTooManyMonitoredItems each, the way Part 4 reports per-item results."""
    held = sum(len(sub.monitored_item_srv._monitored_items)
               for sub in service.subscriptions.values())
    room = max(0, limits.max_monitored_items - held)
    items = params.ItemsToCreate
    if len(items) <= room:
        return await inner(params)
    fitting = []
    if room:
        params.ItemsToCreate = items[:room]
        fitting = await inner(params)
    refused = ua.MonitoredItemCreateResult()
    refused.StatusCode = status_code(ua.StatusCodes.BadTooManyMonitoredItems)
    return [*fitting, *([refused] * (len(items) - room))]


class Door(BinaryServer):
    """The listening side: our connection class, the admission rule and the counts."""

    def __init__(self, iserver: InternalServer, host: Any, port: Any,
                 transport: TransportLimits, limits: OpcUaLimits) -> None:
        super().__init__(iserver, host, port, transport)
        self.door_limits = limits
        self.admission = Limits(usable_connections(limits), limits.max_per_peer,
                                limits.activation_timeout_s, limits.live_window_s)
        self.stats = DoorStats()
        self.channel_check: ChannelCheck | None = None
        self.guard: Guard | None = None
        self._reported = DoorStats()
        self._next_summary_s = 0.0

    def _make_protocol(self) -> Connection:
        return Connection(self)

    def admitted(self) -> list[Connection]:
        return [c for c in list(self.clients) if isinstance(c, Connection) and c.is_open()]

    def admit(self, new: Connection) -> bool:
        slots = {c.key: c for c in self.admitted() if c is not new}
        now_s = time.monotonic()
        decision = decide(new.peer, [c.slot() for c in slots.values()], now_s, self.admission)
        if decision.verdict is Verdict.REFUSE:
            self.count("refused")
            return False
        if decision.verdict is Verdict.EVICT and decision.victim is not None:
            self.count("evicted")
            slots[decision.victim].close()
        self.count("admitted")
        return True

    def count(self, outcome: str) -> None:
        # A new frozen value each time: a test thread may read `stats` at any moment.
        self.stats = replace(self.stats, **{outcome: getattr(self.stats, outcome) + 1})
        now_s = time.monotonic()
        if outcome != "admitted" and now_s >= self._next_summary_s:
            self._summarise(now_s)

    def _summarise(self, now_s: float) -> None:
        said = ", ".join(f"{name} {getattr(self.stats, name) - getattr(self._reported, name)}"
                         for name in DoorStats.__slots__ if name != "admitted"
                         and getattr(self.stats, name) != getattr(self._reported, name))
        log.warning("OPC UA door since the last summary: %s (counts: docs/opcua.md, Limits)",
                    said)
        self._reported = self.stats
        self._next_summary_s = now_s + SUMMARY_S

    async def check_request(self, peer: str, processor: UaProcessor,
                            inner: Callable[..., Any], typeid: ua.NodeId, requesthdr: Any,
                            seqhdr: Any, body: Buffer) -> Any:
        """The processor's dispatch, after the request's size and the session rules."""
        refusal = self._refusal(processor, typeid, body)
        if refusal is not None:
            self.count("requests_refused")
            raise ServiceError(refusal)  # answered as a ServiceFault by asyncua
        if typeid == _CREATE_SESSION:
            await self._make_room_for_session()
        dispatch = partial(inner, typeid, requesthdr, seqhdr, body)
        if self.guard is None:
            return await dispatch()
        return await self.guard(peer, processor, typeid, requesthdr, body, dispatch)

    def _refusal(self, processor: UaProcessor, typeid: ua.NodeId, body: Buffer) -> int | None:
        if typeid == _CREATE_SESSION:
            if processor.session is not None:
                return ua.StatusCodes.BadTooManySessions  # one session per connection
            return None
        asked = operations(typeid, body, self.door_limits)
        if asked is not None and asked[0] > asked[1]:
            return ua.StatusCodes.BadTooManyOperations
        return None

    async def _make_room_for_session(self) -> None:
        """At the session cap, close a session that no connection holds (kept by asyncua
        for a reconnect); if every session has its connection, the new one is refused."""
        sessions = self.iserver._external_sessions
        if len(sessions) < self.door_limits.max_sessions:
            return
        attached = {id(c.processor.session) for c in self.admitted()
                    if c.processor is not None and c.processor.session is not None}
        orphan = next((s for s in sessions.values() if id(s) not in attached), None)
        if orphan is None:
            self.count("requests_refused")
            raise ServiceError(ua.StatusCodes.BadTooManySessions)
        self.count("evicted")
        await orphan.close_session(True)


class Connection(OPCUAProtocol):
    """One client connection, admitted by the door's rule before asyncua sees it."""

    def __init__(self, door: Door) -> None:
        super().__init__(door.iserver, door._policies, door.clients, door.closing_tasks,
                         door.limits)
        self.door = door
        self.peer = "?"
        self.key = str(id(self))
        self.connected_s = time.monotonic()
        # The activation timeout counts the client's time only: since when the server has
        # been waiting for this client (None while a request of its is queued or served:
        # the server's own time, which a busy host stretches, never closes a connection).
        self.waiting_since_s: float | None = self.connected_s
        self.requests = 0

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        peername = transport.get_extra_info("peername")
        self.peer = str(peername[0]) if peername else "?"
        if not self.door.admit(self):
            transport.close()  # never handed to asyncua: no processor, no task, no log
            return
        super().connection_made(transport)
        processor = self.processor
        if processor is not None:
            processor._process_message = partial(  # type: ignore[method-assign]
                self.door.check_request, self.peer, processor, processor._process_message)

    async def _process_one_msg(self, header: Any, buf: Buffer) -> bool:
        self.waiting_since_s = None
        self.requests += 1
        if self.requests > MAX_UNACTIVATED_REQUESTS and not self.activated():
            self.door.count("not_activated")
            self.close()
            return False
        try:
            return await self._process_checked(header, buf)
        finally:
            if self.messages.empty():
                self.waiting_since_s = time.monotonic()

    async def _process_checked(self, header: Any, buf: Buffer) -> bool:
        refusal = self._channel_refusal(header, buf)
        if refusal is None:
            return await super()._process_one_msg(header, buf)
        self.door.count("untrusted")
        if self.transport is not None:  # Part 6: an Error message, then the socket closes
            error = ua.ErrorMessage(status_code(refusal),
                                    ua.String("the client certificate is not trusted"))
            self.transport.write(uatcp_to_binary(ua.MessageType.Error,  # type: ignore[arg-type]
                                                 error))
        self.close()
        return False

    def _channel_refusal(self, header: Any, buf: Buffer) -> int | None:
        """The check of a new secure channel's certificate, from its header alone: nothing
        is decrypted (RSA) for a peer that is refused anyway."""
        check, processor = self.door.channel_check, self.processor
        if check is None or processor is None or processor._connection.is_open() \
                or header.MessageType != ua.MessageType.SecureOpen:
            return None
        try:
            security = struct_from_binary(ua.AsymmetricAlgorithmHeader,
                                          buf.copy(header.body_size))
        except Exception:  # malformed: asyncua answers it as it does
            return None
        return check(self.peer, security.SecurityPolicyURI, security.SenderCertificate)

    def is_open(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()

    def slot(self) -> Slot:
        """Live only with an activated session that made a request lately."""
        processor = self.processor
        last = processor.session_last_activity \
            if processor is not None and self.activated() else None
        return Slot(self.key, self.peer, self.connected_s, last)

    def data_received(self, data: bytes) -> None:
        # asyncua buffers until the size its header announces has arrived: a header claiming
        # 2 GB held 76 MiB per connection. A chunk is never larger than the negotiated buffer.
        head = (self._buffer[:8] + data[:8])[:8]
        if len(head) == 8 and _HEADER.unpack(head)[2] > self.door.limits.max_recv_buffer:
            self.door.count("oversized")
            self._buffer = b""
            self.close()
            return
        super().data_received(data)
        if not self.messages.empty():  # a whole request arrived: the server's turn
            self.waiting_since_s = None

    def activated(self) -> bool:
        session = self.processor.session if self.processor is not None else None
        return session is not None and session.is_activated()

    async def _activation_watchdog(self) -> None:
        """Close a connection without an activated session once the server has waited
        `activation_timeout_s` for its client in one stretch. The time the server spends on
        the client's requests does not count: beside busy processes, at niceness 10, a
        user's scrypt check alone took longer than the timeout, and the client was cut off
        before its answer (asyncio delivers data that arrived while the process waited for
        a CPU before it runs this timer, so a starved server still sees the request first)."""
        timeout_s = self.door.door_limits.activation_timeout_s
        while self.is_open() and not self.activated():
            since = self.waiting_since_s
            left_s = timeout_s if since is None else since + timeout_s - time.monotonic()
            if left_s <= 0:
                self.door.count("not_activated")
                self.close()
                return
            await asyncio.sleep(left_s)
