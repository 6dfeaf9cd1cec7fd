"""The trust list of client certificates in STATE_DIR/pki (OPC UA's secure channels) or
another directory of the state directory (STATE_DIR/modbus-tls: Modbus/TCP Security).

Owns: STATE_DIR/pki/trusted/ and pki/rejected/ (directories 0700, certificates in DER, files
0600), a certificate's name (its subject's common name and the start of its SHA-1
thumbprint, the thumbprint OPC UA uses), whether a certificate is trusted (exactly that
certificate is in trusted/; CA chains are not followed), keeping a refused certificate in
rejected/ for an admin to accept (at most MAX_REJECTED: the oldest go, so a flood of new
certificates cannot fill the disk), and accept/remove by name. trusted/ is listed again when
it changes, so `softplc trust accept` acts on a running server at once.
Does not know: OPC UA, sockets, the CLI.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from softplc.core.errors import SoftplcError

PKI_DIR: Final = "pki"
TRUSTED: Final = "trusted"
REJECTED: Final = "rejected"
MAX_REJECTED: Final = 64
MAX_CERT_BYTES: Final = 16384  # an application certificate is 1-2 KiB; a chain a few
_THUMB_CHARS: Final = 16  # of the 40 hex digits, in names (the whole DER is what is compared)
_UNSAFE: Final = re.compile(r"[^A-Za-z0-9._-]+")


class TrustError(SoftplcError, ValueError):
    """A trust command that cannot be done (no such certificate, an ambiguous name, ...)."""


@dataclass(frozen=True, slots=True)
class Certificate:
    """One certificate of the list, as `softplc trust list` shows it."""

    name: str
    state: str  # trusted, rejected
    subject: str
    uri: str  # the ApplicationUri in its SubjectAltName ("" when none)
    not_after: str
    thumbprint: str


def first_certificate(data: bytes) -> bytes:
    """The leading certificate of a DER chain (a peer may send its chain after it): the
    outer SEQUENCE's length in short or long form (X.690)."""
    if len(data) < 2 or data[0] != 0x30:
        return data
    if data[1] < 0x80:
        return data[:2 + data[1]]
    size = data[1] & 0x7F
    if not 1 <= size <= 4 or len(data) < 2 + size:
        return data
    return data[:2 + size + int.from_bytes(data[2:2 + size], "big")]


def thumbprint(der: bytes) -> str:
    return hashlib.sha1(der, usedforsecurity=False).hexdigest()


def name_of(der: bytes) -> str:
    """`CN_THUMB`: readable, and unique enough to type (trust compares the whole DER)."""
    common = _describe(der)[0].partition("CN=")[2].partition(",")[0] or "certificate"
    return f"{_UNSAFE.sub('-', common).strip('-')[:40] or 'certificate'}_" \
        f"{thumbprint(der)[:_THUMB_CHARS]}"


def _describe(der: bytes) -> tuple[str, str, str]:
    """(subject, ApplicationUri, not after) of a DER certificate; ValueError if it is not one."""
    from cryptography import x509  # only where certificates are looked at

    cert = x509.load_der_x509_certificate(der)
    uris: list[str] = []
    with contextlib.suppress(x509.ExtensionNotFound):
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName)
        uris = san.value.get_values_for_type(x509.UniformResourceIdentifier)
    return (cert.subject.rfc4514_string(), uris[0] if uris else "",
            cert.not_valid_after_utc.strftime("%Y-%m-%dT%H:%MZ"))


class TrustList:
    """The trusted and rejected client certificates of one state directory."""

    def __init__(self, state_dir: Path | str, directory: str = PKI_DIR) -> None:
        self.dir = Path(state_dir) / directory
        self.trusted_dir = self.dir / TRUSTED
        self.rejected_dir = self.dir / REJECTED
        self._seen: tuple[int, tuple[str, ...]] | None = None
        self._trusted: frozenset[bytes] = frozenset()

    def make_dirs(self) -> None:
        for path in (self.dir, self.trusted_dir, self.rejected_dir):
            path.mkdir(mode=0o700, parents=True, exist_ok=True)
            path.chmod(0o700)

    def is_trusted(self, der: bytes) -> bool:
        return der in self._trusted_set()

    def trusted(self) -> frozenset[bytes]:
        """The trusted certificates (DER); the same object until trusted/ changes."""
        return self._trusted_set()

    def _trusted_set(self) -> frozenset[bytes]:
        try:  # the names too: two changes within one mtime tick are still seen
            stamp = (self.trusted_dir.stat().st_mtime_ns,
                     tuple(sorted(os.listdir(self.trusted_dir))))
        except FileNotFoundError:
            return frozenset()
        if stamp != self._seen:
            found = set()
            for path in self.trusted_dir.glob("*.der"):
                with contextlib.suppress(OSError):
                    found.add(path.read_bytes())
            self._seen, self._trusted = stamp, frozenset(found)
        return self._trusted

    def reject(self, der: bytes) -> str | None:
        """Keep a refused certificate in rejected/; its name when it is new there, None when
        it was there already or is no certificate (nothing to accept)."""
        if len(der) > MAX_CERT_BYTES:
            return None
        try:
            name = name_of(der)
        except ValueError:
            return None
        path = self.rejected_dir / f"{name}.der"
        if path.exists():
            return None
        self.make_dirs()
        _write(path, der)
        kept = sorted(self.rejected_dir.glob("*.der"), key=lambda p: p.stat().st_mtime_ns)
        for old in kept[:max(0, len(kept) - MAX_REJECTED)]:
            with contextlib.suppress(OSError):
                old.unlink()
        return name

    def certificates(self) -> list[Certificate]:
        found = []
        for state, directory in ((TRUSTED, self.trusted_dir), (REJECTED, self.rejected_dir)):
            for path in sorted(directory.glob("*.der")) if directory.is_dir() else []:
                der = path.read_bytes()
                try:
                    subject, uri, not_after = _describe(der)
                except ValueError:
                    subject, uri, not_after = "(not a certificate)", "", ""
                found.append(Certificate(path.stem, state, subject, uri, not_after,
                                         thumbprint(der)))
        return found

    def accept(self, name: str) -> Certificate:
        """Trust a rejected certificate (by name or a unique start of it) or a DER/PEM file."""
        file = Path(name)
        if file.is_file() and file.suffix.lower() in (".der", ".pem", ".crt", ".cer"):
            der = _read_certificate(file)
        else:
            der = self._find(name, REJECTED).read_bytes()
        self.make_dirs()
        target = self.trusted_dir / f"{name_of(der)}.der"
        _write(target, der)
        with contextlib.suppress(FileNotFoundError):
            (self.rejected_dir / target.name).unlink()
        return next(c for c in self.certificates() if c.name == target.stem
                    and c.state == TRUSTED)

    def remove(self, name: str) -> Certificate:
        """Forget a trusted or rejected certificate: a trusted one is refused from now on
        (sessions already open keep their channel until they close)."""
        path = self._find(name, None)
        entry = next(c for c in self.certificates() if c.name == path.stem
                     and path.parent.name == c.state)
        path.unlink()
        return entry

    def _find(self, name: str, state: str | None) -> Path:
        entries = [c for c in self.certificates() if state in (None, c.state)]
        exact = [c for c in entries if c.name == name]
        matches = exact or [c for c in entries if c.name.startswith(name) or
                            c.thumbprint.startswith(name.lower())]
        where = f"{state} " if state else ""
        if not matches:
            raise TrustError(f"no {where}certificate {name!r} (softplc trust list)")
        if len(matches) > 1:
            raise TrustError(f"{name!r} names {len(matches)} certificates: "
                             f"{', '.join(c.name for c in matches)}")
        entry = matches[0]
        return (self.trusted_dir if entry.state == TRUSTED else self.rejected_dir) / \
            f"{entry.name}.der"


def _read_certificate(path: Path) -> bytes:
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    data = path.read_bytes()
    try:
        cert = x509.load_pem_x509_certificate(data) if b"-----BEGIN" in data else \
            x509.load_der_x509_certificate(data)
    except ValueError as exc:
        raise TrustError(f"{path}: not a certificate ({exc})") from None
    return cert.public_bytes(Encoding.DER)


def _write(path: Path, data: bytes) -> None:
    """Written aside (0600) and renamed into place: a reader never sees half a certificate."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".cert.")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise

