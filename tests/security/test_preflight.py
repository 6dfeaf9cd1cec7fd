"""security/preflight.py on its own (issue 38, item 4): an expired certificate and a key file
others can read are named at start, with what to do; a clean state directory says nothing."""

from __future__ import annotations

import datetime
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from softplc.security.preflight import check
from softplc.security.settings import SecuritySettings
from softplc.security.tls import TlsSettings


def _pair(where: Path, days: int, mode: int) -> tuple[Path, Path]:
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "plc")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(days=400))
            .not_valid_after(now + datetime.timedelta(days=days))
            .sign(key, hashes.SHA256()))
    cert_path, key_path = where / "cert.pem", where / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                           serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    key_path.chmod(mode)
    return cert_path, key_path


def test_an_expired_certificate_and_an_open_key_file_are_named(tmp_path: Path) -> None:
    cert, key = _pair(tmp_path, days=-1, mode=0o644)
    settings = SecuritySettings(TlsSettings("on", str(cert), str(key)))
    found = check(tmp_path / "state", settings)
    assert found.refused == []
    expired = [w for w in found.warnings if "expired on" in w]
    assert len(expired) == 1 and str(cert) in expired[0] and "replace it" in expired[0]
    readable = [w for w in found.warnings if "readable by others" in w]
    assert len(readable) == 1 and str(key) in readable[0] and "0644" in readable[0] \
        and "chmod 600" in readable[0]


def test_a_clean_state_directory_says_nothing(tmp_path: Path) -> None:
    cert, key = _pair(tmp_path, days=30, mode=0o600)
    found = check(tmp_path / "state", SecuritySettings(TlsSettings("on", str(cert), str(key))),
                  opcua=True)
    assert (found.refused, found.warnings) == ([], [])
