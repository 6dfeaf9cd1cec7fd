"""Audit records of Modbus/TCP Security (secure.py): every write and every refused client.

Owns: the record of a write (who by the certificate, what by describe_write, the outcome by
the reply's exception code) and of a refused TLS client (why; its certificate kept in the
trust list's rejected/ when it was offered and is not trusted), written in the order they
happen by writeaudit.py's AuditWriter (one thread: the loop never waits for the trail's
fsync); the bound on records not yet written (a write beyond it is answered busy by
secure.py, not left unrecorded); at most one record of refused clients per peer and
interval, with the count of those not recorded, so that a client retrying in a loop cannot
rotate the trail's history away.
Does not know: the trail's format and files (security/audit.py) or the trust list's
(security/trust.py): both are handed in as the small protocols below; sockets; TLS.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from typing import Any, Final, Protocol

from softplc.hmi.tlspeer import Identity, describe_write, identity_of
from softplc.hmi.writeaudit import MAX_PENDING, AuditSink, AuditWriter

log = logging.getLogger(__name__)

REFUSAL_INTERVAL_S: Final = 1.0  # per peer
_PEERS_KEPT: Final = 1024  # peers whose last refusal record is remembered


class TrustStore(Protocol):
    """security/trust.py's TrustList: the trusted certificates (DER), the same object until they
    change; `reject` keeps a refused certificate for an admin to accept (blocking)."""

    def trusted(self) -> frozenset[bytes]: ...

    def reject(self, der: bytes) -> str | None: ...


class AuditRecorder:
    """The records of one secure slave; call from its loop, `close()` when it stops."""

    def __init__(self, sink: AuditSink, trust: TrustStore,
                 refusal_interval_s: float = REFUSAL_INTERVAL_S,
                 max_pending: int = MAX_PENDING) -> None:
        self._writer = AuditWriter(sink, max_pending, "Modbus/TCP Security")
        self._trust = trust
        self._refusal_interval_s = refusal_interval_s
        self._last_refusal: OrderedDict[str, tuple[float, int]] = OrderedDict()

    def has_room(self) -> bool:
        return self._writer.has_room()

    def write(self, identity: Identity, peer: str, unit: int, request: bytes,
              reply: bytes) -> None:
        """A write request (PDU) and its reply (PDU): applied, or refused with a code."""
        code = reply[1] if reply[0] & 0x80 and len(reply) > 1 else 0
        outcome = "applied" if code == 0 else "denied" if code == 1 else "refused"
        detail = {**describe_write(request), "unit": unit,
                  "certificate_role": identity.certificate_role}
        entry = {**identity.audit(), "peer": peer, "iface": "modbus", "action": "write",
                 "outcome": outcome, "status": code, "detail": detail}
        self._writer.record(entry)

    def refused(self, peer: str, status: str, error: str, offered: bytes | None,
                now_s: float) -> None:
        """A TLS client refused at the handshake (`status`: no-certificate,
        untrusted-certificate, tls); `offered` is its certificate when it sent one."""
        kept = offered is not None and offered not in self._trust.trusted()
        unrecorded = self._count_refusal(peer, now_s)
        if unrecorded is None:
            if kept and offered is not None and self.has_room():
                self._writer.submit(lambda: self._reject(offered))
            return
        user = None
        if offered is not None:
            try:
                user = identity_of(offered).user
            except ValueError:
                user = None
        entry: dict[str, Any] = {"user": user, "role": None, "via": "certificate", "peer": peer,
                                 "iface": "modbus", "action": "connect", "outcome": "denied",
                                 "status": status, "detail": {
                                     "error": error[:200], "not_recorded_before": unrecorded}}

        def job() -> None:
            if kept and offered is not None:
                entry["detail"]["kept_as"] = self._reject(offered)
            self._writer.append(entry)

        self._writer.submit(job)

    async def close(self) -> None:
        """Wait for the records handed over so far to be written."""
        await self._writer.close()

    def _count_refusal(self, peer: str, now_s: float) -> int | None:
        """How many refusals of `peer` went unrecorded before this one, or None when this
        one is not to be recorded either."""
        last_s, unrecorded = self._last_refusal.pop(peer, (float("-inf"), 0))
        if now_s - last_s < self._refusal_interval_s:
            self._last_refusal[peer] = (last_s, unrecorded + 1)
            return None
        self._last_refusal[peer] = (now_s, 0)
        while len(self._last_refusal) > _PEERS_KEPT:
            self._last_refusal.popitem(last=False)
        return unrecorded

    def _reject(self, der: bytes) -> str | None:
        try:
            return self._trust.reject(der)
        except OSError as exc:
            log.error("refused Modbus/TCP Security certificate not kept: %s", exc)
            return None
