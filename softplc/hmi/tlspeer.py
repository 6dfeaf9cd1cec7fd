"""Who a Modbus/TCP Security client is, and what its requests write: pure functions.

Owns: the role of a client certificate (the spec's "ModbusRole" X.509v3 extension, OID
1.3.6.1.4.1.50316.802.1, an ASN.1 UTF8String) mapped to softplc's role names and whether it
may write; the certificate's user (its subject's common name); the client certificate
offered in a TLS Certificate handshake message (kept when the certificate is refused). The
audit description of a write request is coalesce.py's (re-exported here).
Does not know: sockets, ssl contexts, the trust list, the audit trail, the register map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Final

from cryptography import x509
from cryptography.x509.oid import NameOID

# The description of a write lives with the plain port's audit (coalesce.py, no cryptography).
from softplc.hmi.coalesce import WRITE_FUNCTIONS as WRITE_FUNCTIONS
from softplc.hmi.coalesce import describe_write as describe_write
from softplc.security.decide import Identity as Grant
from softplc.security.decide import granted
from softplc.security.roles import Act, Role

ROLE_OID: Final = x509.ObjectIdentifier("1.3.6.1.4.1.50316.802.1")
# softplc's roles (security/roles.py), lowest first; a role may do what those below it may.
ROLES: Final = tuple(role.label for role in Role)
NO_ROLE: Final = "viewer"  # no role extension, or a role softplc does not know: reads only
# ASN.1 string tags accepted for the role: UTF8String (the spec's), PrintableString, IA5String.
_STRING_TAGS: Final = frozenset({0x0C, 0x13, 0x16})
_TLS_1_3: Final = 0x0304
_CERTIFICATE: Final = 11  # the TLS handshake message type


@dataclass(frozen=True, slots=True)
class Identity:
    """A client as its certificate names it."""

    user: str  # the subject's common name (the whole subject when it has none)
    role: str  # one of ROLES: what softplc grants
    certificate_role: str | None  # the extension's text as written; None when absent

    @property
    def may_write(self) -> bool:
        """Decided where every door's writes are (security/decide.py)."""
        who = Grant(self.user, "certificate", granted=Role.parse(self.role))
        return granted(who, Act.WRITE).allowed

    def audit(self) -> dict[str, Any]:
        return {"user": self.user, "role": self.role, "via": "certificate"}


def identity_of(der: bytes) -> Identity:
    """The identity a DER certificate carries; ValueError if it is no certificate."""
    cert = x509.load_der_x509_certificate(der)
    text = role_text(cert)
    known = (text or "").strip().lower()
    return Identity(user_of(cert), known if known in ROLES else NO_ROLE, text)


def user_of(cert: x509.Certificate) -> str:
    names = cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    value = names[0].value if names else cert.subject.rfc4514_string()
    return value if isinstance(value, str) else value.decode("utf-8", "replace")


def role_text(cert: x509.Certificate) -> str | None:
    """The ModbusRole extension's string, None when the certificate has none or it is not
    a string (then the client gets no role: reads only)."""
    try:
        extension = cert.extensions.get_extension_for_oid(ROLE_OID)
    except x509.ExtensionNotFound:
        return None
    value = extension.value
    if not isinstance(value, x509.UnrecognizedExtension):
        return None
    return der_string(value.value)


def der_string(data: bytes) -> str | None:
    """A DER-encoded ASN.1 string (tag, length, UTF-8 bytes), None when malformed."""
    if len(data) < 2 or data[0] not in _STRING_TAGS:
        return None
    size, start = data[1], 2
    if size & 0x80:
        count = size & 0x7F
        if not 1 <= count <= 2 or len(data) < 2 + count:
            return None
        size, start = int.from_bytes(data[2:2 + count], "big"), 2 + count
    if len(data) != start + size:
        return None
    try:
        return data[start:].decode("utf-8")
    except UnicodeDecodeError:
        return None


def offered_certificate(version: int, message: bytes) -> bytes | None:
    """The first (leaf) certificate, DER, of a TLS Certificate handshake message with its
    4-byte header (RFC 5246 7.4.2; RFC 8446 4.4.2 adds a request context and per-entry
    extensions after each certificate); None for an empty list or a malformed message."""
    if len(message) < 7 or message[0] != _CERTIFICATE:
        return None
    pos = 4
    if version >= _TLS_1_3:
        pos += 1 + message[pos]
    pos += 3  # the list's length: the first entry is all we need
    if len(message) < pos + 3:
        return None
    size = int.from_bytes(message[pos:pos + 3], "big")
    der = message[pos + 3:pos + 3 + size]
    return der if size and len(der) == size else None
