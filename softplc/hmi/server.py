"""The HMI Modbus TCP slave: a pymodbus 3.16 ModbusTcpServer whose connections we own.

Owns: listening, applying the connection rule of admission.py (evict the idle-longest or
refuse), the idle timeout, flow control, moving bytes between sockets and the pure
Responder (frames.py), and handing every write and its answer to the audit of the plain
port (writeaudit.py, when given).
Does not know: the register map (map.py), Modbus semantics (frames.py), the admission rule
itself, how snapshots are published or journaled writes applied, how writes are audited,
TLS (secure.py subclasses the connection: `_connection_factory`, `_reply_stream`, and
audits its own writes).

pymodbus gives the listener and the connection registry that `shutdown()` closes. Every
byte a client sends is handled by `_Connection.data_received`; pymodbus' framer, decoder,
request handler and datastore are never reached (docs/modbus.md, "Design choice").
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import replace
from types import TracebackType
from typing import cast

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.transport import CommParams, CommType, ModbusProtocol

from softplc.core.image import ImageSizes
from softplc.core.snapshot import ChannelFull, HmiWrite, SnapshotSource
from softplc.hmi.admission import (
    DEFAULT_IDLE_TIMEOUT_S,
    DEFAULT_LIVE_WINDOW_S,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_MAX_PER_PEER,
    ConnectionStats,
    Limits,
    Slot,
    Verdict,
    decide,
)
from softplc.hmi.coalesce import WRITE_FUNCTIONS
from softplc.hmi.eng import Presentation
from softplc.hmi.frames import (
    Adu,
    FramingError,
    Responder,
    encode_adu,
    exception_pdu,
    split_adu,
)
from softplc.hmi.map import ExceptionCode, RegisterMap, Table, Writable
from softplc.hmi.writeaudit import WriteAudit, WritesAudited

log = logging.getLogger(__name__)

DEFAULT_PORT = 5020
ERROR_LOG_INTERVAL_S = 10.0


class _RateLimitedErrors:
    """Logs a failure at most once per interval, with how many were skipped; `trace`: with
    the traceback (an unexpected failure), else one line (an expected refusal)."""

    def __init__(self, interval_s: float = ERROR_LOG_INTERVAL_S) -> None:
        self._interval_s = interval_s
        self._next_s = 0.0
        self._skipped = 0

    def report(self, what: str, *, trace: bool = True) -> None:
        now_s = time.monotonic()
        if now_s < self._next_s:
            self._skipped += 1
            return
        (log.exception if trace else log.warning)("%s (%d similar not logged)", what,
                                                  self._skipped)
        self._skipped = 0
        self._next_s = now_s + self._interval_s


class _Connection(ModbusProtocol):
    """One HMI connection. Requests are answered in arrival order, several per segment if
    the client pipelines; nothing is awaited, so a reply is written before the next request
    is looked at."""

    def __init__(self, owner: _Listener) -> None:
        params = CommParams(comm_name="hmi", comm_type=CommType.TCP)
        params.source_address = owner.comm_params.source_address
        super().__init__(params, True)
        self._owner = owner
        self._responder = owner.responder
        self._errors = owner.errors
        self._idle_timeout_s = owner.limits.idle_timeout_s
        self._buffer = b""
        self._writing_paused = False
        self.admitted = False
        self.peer = ""
        self._connected_s = 0.0
        self._last_request_s: float | None = None
        self._idle_timer: asyncio.TimerHandle | None = None

    def callback_connected(self) -> None:
        peername = self.transport.get_extra_info("peername")
        self.peer = str(peername[0]) if peername else "?"
        self._connected_s = self.loop.time()
        if not self._owner.admit(self):
            self.close()
            return
        self.admitted = True
        self._idle_timer = self.loop.call_later(self._idle_timeout_s, self._check_idle)

    def slot(self) -> Slot:
        return Slot(self.unique_id, self.peer, self._connected_s, self._last_request_s)

    def callback_disconnected(self, exc: Exception | None) -> None:
        self._stop_idle_timer()

    def callback_data(self, data: bytes, addr: tuple[str, int] | None = None) -> int:
        raise AssertionError("unreachable: data_received is overridden")

    def callback_new_connection(self) -> ModbusProtocol:
        raise AssertionError("unreachable: a connection does not accept connections")

    def close(self, reconnect: bool = False) -> None:
        self._stop_idle_timer()
        super().close(reconnect)

    @property
    def buffered_bytes(self) -> int:
        """Requests not yet answered plus replies not yet sent, in bytes."""
        stream = self._reply_stream()
        unsent = 0 if stream is None else stream.get_write_buffer_size()
        return len(self._buffer) + unsent

    def data_received(self, data: bytes) -> None:
        self._requests_received(data)

    def _requests_received(self, data: bytes) -> None:
        self._buffer += data
        self._serve_buffer()

    def _serve_buffer(self) -> None:
        # While the client does not read, requests stay unparsed in `_buffer` (reading is
        # paused, so it holds at most one segment): replies never pile up beyond the
        # transport's high-water mark plus one reply.
        buffer, pos = self._buffer, 0
        while self._can_answer():
            try:
                adu, end = split_adu(buffer, pos)
            except FramingError as exc:
                log.info("HMI connection closed: %s", exc)
                self.close()
                return
            if adu is None:
                break
            pos = end
            self._last_request_s = self.loop.time()
            if (reply := self._answer(adu)) is not None:
                self._stream.write(reply)
        self._buffer = buffer[pos:]

    def _can_answer(self) -> bool:
        # A transport that is closing (the client reset) would log every further write.
        stream = self._reply_stream()
        return stream is not None and not stream.is_closing() and not self._writing_paused

    def pause_writing(self) -> None:
        self._replies_blocked()

    def resume_writing(self) -> None:
        self._replies_unblocked()

    def _replies_blocked(self) -> None:
        # The client does not read its replies: stop reading its requests until it does.
        self._writing_paused = True
        self._stream.pause_reading()

    def _replies_unblocked(self) -> None:
        self._writing_paused = False
        self._stream.resume_reading()
        self._serve_buffer()

    def _reply_stream(self) -> asyncio.Transport | None:
        """Where requests come from and replies go: the socket (a TLS session in secure.py)."""
        return cast("asyncio.Transport | None", self.transport)

    @property
    def _stream(self) -> asyncio.Transport:
        return cast(asyncio.Transport, self._reply_stream())

    def _answer(self, adu: Adu) -> bytes | None:
        reply = self._respond(adu)
        audit = self._owner.audit
        if audit is not None and reply is not None and adu.pdu[0] in WRITE_FUNCTIONS:
            try:
                audit.write(self.peer, adu.unit_id, adu.pdu, reply[7:], self.loop.time())
            except Exception:  # the write is answered; its record must not break the reply
                self._errors.report("HMI write audit failed")
        return reply

    def _respond(self, adu: Adu) -> bytes | None:
        try:
            return self._responder.answer(adu)
        except ChannelFull as exc:  # the scan does not drain HMI writes: busy, retry (HTTP 503)
            self._owner.busy.report(f"HMI write answered 06 (busy): {exc}", trace=False)
            code = ExceptionCode.SERVER_DEVICE_BUSY
        except Exception:  # the snapshot source or the write sink failed: a bug, 04
            self._errors.report("HMI request failed")
            code = ExceptionCode.SERVER_DEVICE_FAILURE
        return encode_adu(adu.transaction_id, adu.unit_id, exception_pdu(adu.pdu[0], code))

    def _check_idle(self) -> None:
        idle_s = self.loop.time() - self.slot().last_active_s
        if idle_s >= self._idle_timeout_s:
            log.info("HMI connection from %s closed: idle for %.1f s", self.peer, idle_s)
            self._idle_timer = None
            self._owner.count("idle_closed")
            self.close()
            return
        remaining_s = self._idle_timeout_s - idle_s
        self._idle_timer = self.loop.call_later(remaining_s, self._check_idle)

    def _stop_idle_timer(self) -> None:
        if self._idle_timer is not None:
            self._idle_timer.cancel()
            self._idle_timer = None


def _placeholder_device() -> SimDevice:
    # ModbusTcpServer insists on a datastore; our connections never consult it.
    return SimDevice(id=0, simdata=[SimData(0, values=[0], datatype=DataType.REGISTERS)])


ConnectionFactory = Callable[["_Listener"], _Connection]


class _Listener(ModbusTcpServer):
    """The pymodbus listener, with our connection class and the admission rule."""

    def __init__(self, responder: Responder, address: tuple[str, int], limits: Limits,
                 make_connection: ConnectionFactory = _Connection) -> None:
        super().__init__(_placeholder_device(), address=address)
        self.responder = responder
        self.errors, self.busy = _RateLimitedErrors(), _RateLimitedErrors()  # busy hides no bug
        self.limits = limits
        self.stats = ConnectionStats()
        self.audit: WriteAudit | None = None
        self._make_connection = make_connection

    def callback_new_connection(self) -> _Connection:
        # The peer is not known yet: the connection asks `admit` once it is connected.
        return self._make_connection(self)

    def admitted(self) -> list[_Connection]:
        # One C-level copy first: a test thread may ask while the loop thread changes the dict.
        connections = list(self.active_connections.values())
        return [c for c in connections if isinstance(c, _Connection) and c.admitted]

    def admit(self, new: _Connection) -> bool:
        """Apply the admission rule to `new`; closes the evicted connection, if any."""
        slots = {c.unique_id: c for c in self.admitted() if c is not new}
        decision = decide(
            new.peer, [c.slot() for c in slots.values()], self.loop.time(), self.limits
        )
        if decision.verdict is Verdict.REFUSE:
            log.debug("HMI connection from %s refused: %s", new.peer, decision.reason)
            self.count("refused")
            return False
        if decision.verdict is Verdict.EVICT and decision.victim is not None:
            victim = slots[decision.victim]
            log.debug(
                "HMI connection from %s closed for one from %s: %s",
                victim.peer,
                new.peer,
                decision.reason,
            )
            self.count("evicted")
            victim.close()
        self.count("admitted")
        return True

    def count(self, outcome: str) -> None:
        # A new frozen value each time: another thread may read `stats` at any moment.
        self.stats = replace(self.stats, **{outcome: getattr(self.stats, outcome) + 1})


class ModbusSlave:
    """Modbus TCP slave for HMIs. Reads answer from `source.latest()`; writes are passed to
    `sink` as HmiWrite journal entries and show up only in a later published snapshot.
    Runs on the asyncio loop that calls `start()`; `source` and `sink` are called there.
    `audit`: every write (function 5, 6, 15, 16, 23) and its outcome go to the audit trail,
    coalesced (docs/security.md, "Audit of plain Modbus writes")."""

    def __init__(
        self,
        source: SnapshotSource,
        sink: Callable[[HmiWrite], None],
        *,
        sizes: ImageSizes,
        host: str = "127.0.0.1",
        port: int = DEFAULT_PORT,
        writable: Writable | None = None,
        read_only: bool = False,
        max_connections: int = DEFAULT_MAX_CONNECTIONS,
        max_per_peer: int | None = None,
        idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S,
        live_window_s: float = DEFAULT_LIVE_WINDOW_S,
        audit: WritesAudited | None = None,
        presentation: Presentation | None = None,
    ) -> None:
        per_peer = (
            min(DEFAULT_MAX_PER_PEER, max_connections) if max_per_peer is None else max_per_peer
        )
        self.limits = Limits(
            max_connections, per_peer, idle_timeout_s, min(live_window_s, idle_timeout_s)
        )
        self.map = RegisterMap(sizes, writable=writable, read_only=read_only,
                               presentation=presentation)  # scaled symbols (eng.py)
        self._responder = Responder(self.map, source, sink)
        self.host = host
        self.port = port
        self.audit = audit
        self._listener: _Listener | None = None
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        """Listen; returns once connections are accepted. Port 0 picks a free port."""
        if self._listener is not None:
            raise RuntimeError("the Modbus slave is already started")
        listener = _Listener(self._responder, (self.host, self.port), self.limits,
                             self._connection_factory())
        if self.audit is not None:
            listener.audit = WriteAudit(self.audit, lambda t, a: self.map.where(Table(t), a))
        try:
            await listener.serve_forever(background=True)
        except RuntimeError as exc:
            raise OSError(f"Modbus slave cannot listen on {self.host}:{self.port}") from exc
        self._listener = listener
        self._server = cast(asyncio.Server, listener.transport)

    def _connection_factory(self) -> ConnectionFactory:
        """The class of a connection (Modbus/TCP Security's in secure.py)."""
        return _Connection

    async def stop(self) -> None:
        """Stop listening, close every HMI connection, write the audit's open counts."""
        listener, server = self._listener, self._server
        self._listener = self._server = None
        if listener is None or server is None:
            return
        await listener.shutdown()  # type: ignore[no-untyped-call]
        await server.wait_closed()
        if listener.audit is not None:
            await listener.audit.close()

    @property
    def bound_port(self) -> int:
        if self._server is None:
            raise RuntimeError("the Modbus slave is not started")
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def max_connections(self) -> int:
        return self.limits.max_connections

    @property
    def idle_timeout_s(self) -> float:
        return self.limits.idle_timeout_s

    @property
    def connection_count(self) -> int:
        """Admitted connections that are open."""
        return 0 if self._listener is None else len(self._listener.admitted())

    @property
    def connection_stats(self) -> ConnectionStats:
        return ConnectionStats() if self._listener is None else self._listener.stats

    @property
    def buffered_bytes(self) -> int:
        """Bytes held for all connections (unparsed requests, unsent replies): bounded by
        the connection limit times one read segment plus the write high-water mark."""
        if self._listener is None:
            return 0
        connections = list(self._listener.active_connections.values())
        return sum(c.buffered_bytes for c in connections if isinstance(c, _Connection))

    async def __aenter__(self) -> ModbusSlave:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()
