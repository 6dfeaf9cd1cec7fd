"""The OPC UA server's own certificate and key in STATE_DIR/pki/own (issue 31).

Owns: making the key (RSA 2048: what Basic256Sha256 and both Aes policies accept; PEM, 0600)
and a self-signed application instance certificate at the first start (SubjectAltName: the
server's ApplicationUri, which Part 4 requires to match, and the host's names; the key and
extended key uses of OPC UA Part 6's application certificates), and a new certificate for the
same key when the ApplicationUri changed (another port). Blocking: run it in a thread.
Does not know: asyncua's server, the trust list of clients (security/trust.py), sessions.
"""

from __future__ import annotations

import datetime
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import rsa
from cryptography.x509.oid import ExtendedKeyUsageOID

from softplc.security.certnames import alt_names, subject
from softplc.security.files import write_private
from softplc.security.trust import PKI_DIR, TrustList, thumbprint

log = logging.getLogger(__name__)

OWN: Final = "own"
CERT_FILE: Final = "cert.der"
KEY_FILE: Final = "key.pem"
KEY_BITS: Final = 2048
VALID_DAYS: Final = 5 * 365
EARLY: Final = datetime.timedelta(days=1)  # valid from yesterday: a peer's clock a bit behind


@dataclass(frozen=True, slots=True)
class ServerIdentity:
    cert: Path
    key: Path
    thumbprint: str
    made: bool  # a certificate was made at this start


def server_identity(state_dir: Path, application_uri: str, hosts: list[str]) -> ServerIdentity:
    """The certificate and key to serve with, made when missing or when the certificate does
    not name `application_uri` (the key is kept)."""
    TrustList(state_dir).make_dirs()
    own = Path(state_dir) / PKI_DIR / OWN
    own.mkdir(mode=0o700, exist_ok=True)
    own.chmod(0o700)
    cert_path, key_path = own / CERT_FILE, own / KEY_FILE
    key = _load_or_make_key(key_path)
    der = cert_path.read_bytes() if cert_path.exists() else b""
    if der and _names_uri(der, application_uri):
        return ServerIdentity(cert_path, key_path, thumbprint(der), made=False)
    if der:
        log.warning("the OPC UA certificate names another ApplicationUri: a new one is made for "
                    "%s (clients that trusted the old one must trust this one)", application_uri)
    der = _self_signed(key, application_uri, hosts)
    write_private(cert_path, der)
    log.info("OPC UA server certificate made: %s (SHA-1 %s)", cert_path, thumbprint(der))
    return ServerIdentity(cert_path, key_path, thumbprint(der), made=True)


def _load_or_make_key(path: Path) -> rsa.RSAPrivateKey:
    if path.exists():
        if path.stat().st_mode & 0o077:
            path.chmod(0o600)
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
        if isinstance(key, rsa.RSAPrivateKey):
            return key
        raise ValueError(f"{path} is not an RSA key; remove it to get a new one")
    key = rsa.generate_private_key(public_exponent=65537, key_size=KEY_BITS)
    write_private(path, key.private_bytes(serialization.Encoding.PEM,
                                   serialization.PrivateFormat.PKCS8,
                                   serialization.NoEncryption()))
    return key


def _names_uri(der: bytes, uri: str) -> bool:
    try:
        cert = x509.load_der_x509_certificate(der)
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName)
    except (ValueError, x509.ExtensionNotFound):
        return False
    fresh = cert.not_valid_after_utc > datetime.datetime.now(datetime.UTC) + EARLY
    return fresh and uri in san.value.get_values_for_type(x509.UniformResourceIdentifier)


def _self_signed(key: rsa.RSAPrivateKey, uri: str, hosts: list[str]) -> bytes:
    name = subject(hosts[0])
    now = datetime.datetime.now(datetime.UTC)
    builder = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - EARLY)
               .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
               .add_extension(alt_names(hosts, uri), critical=False)
               # self-signed: its own issuer, as asyncua's and UA-.NET's own certificates are
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
               .add_extension(x509.KeyUsage(
                   digital_signature=True, content_commitment=True, key_encipherment=True,
                   data_encipherment=True, key_agreement=False, key_cert_sign=True,
                   crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
               .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                     ExtendedKeyUsageOID.CLIENT_AUTH]),
                              critical=False)
               .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()),
                              critical=False))
    return builder.sign(key, hashes.SHA256()).public_bytes(serialization.Encoding.DER)


