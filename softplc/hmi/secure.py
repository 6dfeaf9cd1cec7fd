"""Modbus/TCP Security (the Modbus Organization's "mbaps", port 802): the HMI slave of
server.py over mutual TLS, writes decided by the role in the client's certificate.

Owns: TlsConfig; the server's TLS context (TLS 1.2 at least, a client certificate required
and verified against the trust list, rebuilt when trusted/ changes; no compression,
renegotiation or session tickets); the TLS session inside each admitted connection, so that
server.py's admission rule, per-peer cap and idle timeout hold before and during the
handshake; catching the certificate a refused client offered (to keep it in rejected/);
answering a write of a client whose role may not write with exception 01, as the spec's
role-based authorization does; handing every write and refused client to tlsaudit.py.
Does not know: where the certificates are made or the trust list's and the trail's files
(handed in: security/tls.py, security/trust.py, security/audit.py); Modbus semantics (frames.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
from asyncio.sslproto import SSLProtocol
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, cast

from softplc.core.errors import SoftplcError
from softplc.core.image import ImageSizes
from softplc.core.snapshot import HmiWrite, SnapshotSource
from softplc.hmi.frames import Adu, encode_adu, exception_pdu
from softplc.hmi.map import ExceptionCode
from softplc.hmi.server import ConnectionFactory, ModbusSlave, _Connection, _Listener
from softplc.hmi.tlsaudit import REFUSAL_INTERVAL_S, AuditRecorder, TrustStore
from softplc.hmi.tlspeer import WRITE_FUNCTIONS, Identity, identity_of, offered_certificate
from softplc.hmi.writeaudit import AuditSink

log = logging.getLogger(__name__)

DEFAULT_TLS_PORT: Final = 802  # IANA's mbap-s
MODBUS_TLS_DIR: Final = "modbus-tls"  # in the state directory: trusted/, rejected/, tls/
HANDSHAKE_TIMEOUT_S: Final = 10  # a handshake is a few round trips
_HANDSHAKE: Final = 22  # TLS content type
_CERTIFICATE: Final = 11  # TLS handshake message type


class SecureSlaveError(SoftplcError, ValueError):
    """The slave's certificate or key cannot be used; one line naming the files."""


@dataclass(frozen=True, slots=True)
class TlsConfig:
    """The server's certificate and key (PEM), the trust list of client certificates and the
    audit trail. `refusal_interval_s`: at most one record of refused clients per peer."""

    cert: Path
    key: Path
    trust: TrustStore
    audit: AuditSink
    handshake_timeout_s: int = HANDSHAKE_TIMEOUT_S
    refusal_interval_s: float = REFUSAL_INTERVAL_S


class _Contexts:
    """The TLS context of the current trust list, and the certificate each handshake offers:
    OpenSSL refuses an untrusted one without showing it, but its message callback sees the
    client's Certificate message in the clear (TLS 1.3 included) while the connection being
    fed (`feeding`) is known."""

    def __init__(self, config: TlsConfig) -> None:
        self._config = config
        self._trusted: frozenset[bytes] | None = None
        self._context: ssl.SSLContext | None = None
        self.feeding: _TlsConnection | None = None

    def current(self) -> ssl.SSLContext:
        trusted = self._config.trust.trusted()
        if self._context is None or trusted is not self._trusted:
            self._context, self._trusted = self._build(trusted), trusted
        return self._context

    def _build(self, trusted: frozenset[bytes]) -> ssl.SSLContext:
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.minimum_version = ssl.TLSVersion.TLSv1_2
        # No renegotiation (the spec forbids it), compression (CRIME) or resumption: a
        # certificate removed from trusted/ must not come back through a saved session.
        context.options |= ssl.OP_NO_COMPRESSION | ssl.OP_NO_RENEGOTIATION | ssl.OP_NO_TICKET
        context.num_tickets = 0
        context.verify_mode = ssl.CERT_REQUIRED
        # A trusted certificate is an anchor by itself, whoever issued it; a trusted CA
        # vouches for the certificates it issued (the spec's usual setup).
        context.verify_flags |= ssl.VERIFY_X509_PARTIAL_CHAIN
        config = self._config
        try:
            context.load_cert_chain(config.cert, config.key)
        except (OSError, ssl.SSLError) as exc:
            raise SecureSlaveError(f"certificate {config.cert} with key {config.key} cannot "
                                   f"be used: {exc}") from None
        for der in trusted:
            try:
                context.load_verify_locations(cadata=der)
            except ssl.SSLError as exc:
                log.warning("a trusted Modbus/TCP Security certificate is unusable: %s", exc)
        context._msg_callback = self._message  # type: ignore[attr-defined]
        return context

    def _message(self, conn: object, direction: str, version: int, content_type: int,
                 msg_type: int, data: bytes) -> None:
        # Called inside OpenSSL: an exception here would fail the handshake.
        feeding = self.feeding
        if feeding is None or direction != "read" or content_type != _HANDSHAKE \
                or msg_type != _CERTIFICATE:
            return
        with contextlib.suppress(Exception):
            feeding.offered = offered_certificate(int(version), data)


class _Guard:
    """What the connections of one secure slave share."""

    def __init__(self, config: TlsConfig) -> None:
        self.config = config
        self.contexts = _Contexts(config)
        self.recorder = AuditRecorder(config.audit, config.trust, config.refusal_interval_s)

    def factory(self) -> ConnectionFactory:
        return lambda listener: _TlsConnection(listener, self)


class _Decrypted(asyncio.Protocol):
    """The application side of a connection's TLS session."""

    def __init__(self, connection: _TlsConnection) -> None:
        self._connection = connection

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._connection.secured(cast(asyncio.Transport, transport))

    def data_received(self, data: bytes) -> None:
        self._connection.requests(data)

    def pause_writing(self) -> None:
        self._connection.session_blocked()

    def resume_writing(self) -> None:
        self._connection.session_unblocked()

    def eof_received(self) -> bool | None:
        return None  # the session closes: never half-open

    def connection_lost(self, exc: Exception | None) -> None:
        pass  # the socket's side (_TlsConnection.connection_lost) ends the connection


class _TlsConnection(_Connection):
    """A connection of server.py whose bytes pass through TLS once it is admitted; requests
    are served after the handshake, by the rights of the client certificate's role."""

    def __init__(self, owner: _Listener, guard: _Guard) -> None:
        super().__init__(owner)
        self._guard = guard
        self._tls: SSLProtocol | None = None
        self._session: asyncio.Transport | None = None
        self.identity: Identity | None = None
        self.offered: bytes | None = None  # the certificate of the handshake, if any

    def callback_connected(self) -> None:
        super().callback_connected()
        if not self.admitted:
            return
        try:
            context = self._guard.contexts.current()
        except SecureSlaveError as exc:
            log.error("Modbus/TCP Security connection from %s closed: %s", self.peer, exc)
            self.close()
            return
        handshake = self.loop.create_future()
        handshake.add_done_callback(self._handshake_done)
        self._tls = SSLProtocol(self.loop, _Decrypted(self), context, handshake,
                                server_side=True,
                                ssl_handshake_timeout=self._guard.config.handshake_timeout_s)
        self._tls.connection_made(self.transport)

    def data_received(self, data: bytes) -> None:
        tls = self._tls
        if tls is None:
            return
        contexts = self._guard.contexts
        contexts.feeding = self
        try:
            view = memoryview(data)
            while view:
                buffer = tls.get_buffer(len(view))
                size = min(len(buffer), len(view))
                buffer[:size] = view[:size]
                tls.buffer_updated(size)
                view = view[size:]
        finally:
            contexts.feeding = None

    def eof_received(self) -> None:
        if self._tls is not None:
            self._tls.eof_received()

    def pause_writing(self) -> None:
        if self._tls is not None:
            self._tls.pause_writing()

    def resume_writing(self) -> None:
        if self._tls is not None:
            self._tls.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        tls, self._tls, self._session = self._tls, None, None
        if tls is not None:
            tls.connection_lost(exc)
        super().connection_lost(exc)

    def _reply_stream(self) -> asyncio.Transport | None:
        return self._session

    # -- the TLS session's side (_Decrypted) ---------------------------------------------

    def secured(self, session: asyncio.Transport) -> None:
        ssl_object = session.get_extra_info("ssl_object")
        der = ssl_object.getpeercert(binary_form=True) if ssl_object is not None else None
        try:
            self.identity = identity_of(der) if der else None
        except ValueError:
            self.identity = None
        if self.identity is None:  # OpenSSL required a certificate: not expected
            log.error("Modbus/TCP Security client %s: no readable certificate", self.peer)
            self.close()
            return
        log.info("Modbus/TCP Security client %s from %s, role %s (certificate: %r)",
                 self.identity.user, self.peer, self.identity.role,
                 self.identity.certificate_role)
        self._session = session

    def requests(self, data: bytes) -> None:
        self._requests_received(data)

    def session_blocked(self) -> None:
        self._replies_blocked()

    def session_unblocked(self) -> None:
        self._replies_unblocked()

    def _handshake_done(self, handshake: asyncio.Future[None]) -> None:
        if handshake.cancelled() or handshake.exception() is None:
            return
        exc = handshake.exception()
        if not isinstance(exc, ssl.SSLError):  # closed or timed out before a TLS verdict
            log.debug("Modbus/TCP Security handshake with %s ended: %r", self.peer, exc)
            return
        if isinstance(exc, ssl.SSLCertVerificationError):
            status = "untrusted-certificate"
        elif "PEER_DID_NOT_RETURN_A_CERTIFICATE" in str(exc.reason):
            status = "no-certificate"
        else:
            status = "tls"
        log.info("Modbus/TCP Security client %s refused: %s", self.peer, exc)
        self._guard.recorder.refused(self.peer, status, str(exc), self.offered,
                                     self.loop.time())

    def _answer(self, adu: Adu) -> bytes | None:
        identity = self.identity
        if identity is None or adu.protocol_id != 0 or adu.pdu[0] not in WRITE_FUNCTIONS:
            return self._respond(adu)
        recorder = self._guard.recorder
        if not recorder.has_room():  # the trail lags: no write goes unrecorded
            log.warning("Modbus/TCP Security write of %s refused: the audit trail lags",
                        identity.user)
            return _refusal(adu, ExceptionCode.SERVER_DEVICE_BUSY)
        reply = (self._respond(adu) if identity.may_write
                 else _refusal(adu, ExceptionCode.ILLEGAL_FUNCTION))
        if reply is not None:
            recorder.write(identity, self.peer, adu.unit_id, adu.pdu, reply[7:])
        return reply


def _refusal(adu: Adu, code: ExceptionCode) -> bytes:
    return encode_adu(adu.transaction_id, adu.unit_id, exception_pdu(adu.pdu[0], code))


class SecureModbusSlave(ModbusSlave):
    """ModbusSlave speaking Modbus/TCP Security: `tls` names the certificates, the trust
    list and the audit trail; `options` are ModbusSlave's (writable, read_only, limits),
    applied after the role: a viewer's write is 01, a write the policy refuses 02."""

    def __init__(self, source: SnapshotSource, sink: Callable[[HmiWrite], None], *,
                 tls: TlsConfig, sizes: ImageSizes, host: str = "127.0.0.1",
                 port: int = DEFAULT_TLS_PORT, **options: Any) -> None:
        super().__init__(source, sink, sizes=sizes, host=host, port=port, **options)
        self.tls = tls
        self._guard: _Guard | None = None

    def _connection_factory(self) -> ConnectionFactory:
        assert self._guard is not None
        return self._guard.factory()

    async def start(self) -> None:
        """Listen; SecureSlaveError when the certificate or key cannot be used."""
        guard = _Guard(self.tls)
        guard.contexts.current()
        self._guard = guard
        await super().start()

    async def stop(self) -> None:
        """Stop listening, close every connection, write the audit records still pending."""
        guard = self._guard
        await super().stop()
        if guard is not None:
            await guard.recorder.close()
