"""HTTPS for the API: the server's certificate, the TLS contexts of server and client.

Owns: when TLS is on (`on`, `off`, `auto`: off on a loopback bind, on elsewhere), the
certificate made at the first start in STATE_DIR/tls/ (ECDSA P-256, self-signed, 10 years,
naming localhost, the loopback addresses, the host's name and the bind address; key 0600)
or the one given, the server's context (TLS 1.2 at least), and the client's (a CA file; one
that holds a single self-signed certificate that is no CA is a pin: the server must present
exactly it, whatever name the URL uses).
Does not know: aiohttp's sites (tlsproto.py), routes, the CLI.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import socket
import ssl
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

from softplc.core.errors import SoftplcError
from softplc.security.auth import is_loopback
from softplc.security.files import write_private

TLS_DIR: Final = "tls"
CERT_FILE: Final = "cert.pem"
KEY_FILE: Final = "key.pem"
VALID_DAYS: Final = 3650
EARLY: Final = datetime.timedelta(days=1)  # valid from yesterday: a client's clock behind
MODES: Final = ("auto", "on", "off")
Mode = Literal["auto", "on", "off"]


class TlsError(SoftplcError, ValueError):
    """A certificate or key that cannot be used; one line naming the file."""


@dataclass(frozen=True, slots=True)
class TlsSettings:
    """`softplc run --tls MODE [--tls-cert FILE --tls-key FILE]`; no cert: the generated one."""

    mode: Mode = "off"
    cert: str | None = None
    key: str | None = None

    def wanted(self, host: str) -> bool:
        return self.mode == "on" or (self.mode == "auto" and not is_loopback(host))


def generated_paths(state_dir: Path) -> tuple[Path, Path]:
    directory = Path(state_dir) / TLS_DIR
    return directory / CERT_FILE, directory / KEY_FILE


def certificate(settings: TlsSettings, state_dir: Path, host: str) -> tuple[Path, Path, bool]:
    """The certificate and key to serve with, and whether they were made now. Blocking."""
    if settings.cert and settings.key:
        return Path(settings.cert), Path(settings.key), False
    cert, key = generated_paths(state_dir)
    if cert.exists() and key.exists():
        if key.stat().st_mode & 0o077:
            key.chmod(0o600)
        return cert, key, False
    cert.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    cert_pem, key_pem = _self_signed(host)
    write_private(key, key_pem)
    write_private(cert, cert_pem)
    cert.chmod(0o644)  # public: what clients are given to verify the PLC
    return cert, key, True


def server_context(cert: Path, key: Path) -> ssl.SSLContext:
    """TLS 1.2 or later only; OpenSSL's default ciphers of this version."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.options |= ssl.OP_NO_COMPRESSION  # CRIME
    try:
        context.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise TlsError(f"certificate {cert} with key {key} cannot be used: {exc}") from None
    return context


def client_context(ca: Path | None) -> ssl.SSLContext:
    """Verify the server against `ca` (None: the system's CAs), TLS 1.2 or later."""
    context = ssl.create_default_context(cafile=None if ca is None else str(ca))
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    stats = context.cert_store_stats()
    if ca is not None and stats["x509"] == 1 and stats["x509_ca"] == 0:
        # One self-signed leaf: only the holder of its key passes the handshake; its names
        # add nothing, and a PLC reached by an address it was not made for still verifies.
        context.check_hostname = False
    return context


def fingerprint(cert: Path) -> str:
    """SHA-256 of the certificate (DER), as browsers and `openssl x509 -fingerprint` show."""
    der = ssl.PEM_cert_to_DER_cert(cert.read_text(encoding="ascii"))
    digest = hashlib.sha256(der).hexdigest().upper()
    return ":".join(digest[i:i + 2] for i in range(0, len(digest), 2))


def _names(host: str) -> list[str]:
    names = ["localhost", "127.0.0.1", "::1"]
    with contextlib.suppress(OSError):
        names += [socket.gethostname(), socket.getfqdn()]
    if host and host not in ("0.0.0.0", "::"):
        names.append(host)
    return list(dict.fromkeys(n for n in names if n))


def _self_signed(host: str) -> tuple[bytes, bytes]:
    from cryptography import x509  # only when a certificate is made
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID

    from softplc.security.certnames import alt_names, subject

    key = ec.generate_private_key(ec.SECP256R1())
    names = _names(host)
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(subject(names[-1]))
            .issuer_name(subject(names[-1]))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - EARLY)
            .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
            .add_extension(alt_names(names), critical=False)
            # Not a CA: it can vouch for nothing but itself (client_context's pin rule).
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]),
                           critical=False)
            .sign(key, hashes.SHA256()))
    key_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                serialization.NoEncryption())
    return cert.public_bytes(serialization.Encoding.PEM), key_pem


