"""Signed programs: an engineer's Ed25519 key pair, the detached signature of the exact bytes
a download carries (program text or bundle zip) with the program's version, and a PLC's
trusted keys.

Owns: the key files (`NAME.key`, PKCS#8 PEM, mode 0600; `NAME.pub`, SubjectPublicKeyInfo
PEM: what a PLC trusts), the signature line (`ed25519 SHA256:FINGERPRINT BASE64` and, when
versioned, ` version=N`; the same in a `.sig` file and in the `X-Softplc-Signature` header),
the signed message (the version is signed with the bytes), signing, and `TrustedKeys.verify`
naming the signer and the version or raising `SignatureRefused` with one line of reason.
Does not know: HTTP, the scan, where the trusted keys directory is configured, which
version runs (programgate.py, versions.py).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)

from softplc.core.errors import SoftplcError
from softplc.core.snapshot import DOWNLOAD_REFUSED

ALGORITHM: Final = "ed25519"
# Domain separation: a signature made for a softplc download is good for nothing else.
CONTEXT: Final = b"softplc program signature 1\n"
# A versioned signature signs CONTEXT_VERSIONED + b"version N\n" + the bytes: the version
# cannot be edited, added or stripped without breaking it, and neither message is the other's.
CONTEXT_VERSIONED: Final = b"softplc program signature 2\n"
MAX_VERSION: Final = 10**18 - 1  # 18 digits, canonical decimal: one text per version
MAX_KEYS: Final = 256
_NAME: Final = re.compile(r"[a-z][a-z0-9_-]{0,31}")
_LINE: Final = re.compile(r"ed25519 (SHA256:[A-Za-z0-9+/]{43}) ([A-Za-z0-9+/]{86}==)"
                          r"(?: version=(0|[1-9][0-9]{0,17}))?")


class SigningError(SoftplcError, ValueError):
    """A key or signature file that cannot be used (missing, malformed, open to others)."""


class SignatureRefused(SoftplcError):
    """A download this PLC does not take: `reason` is one line, `DOWNLOAD_REFUSED: ...`."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def fingerprint(public: Ed25519PublicKey) -> str:
    """`SHA256:` and the unpadded base64 of the raw key's SHA-256, as OpenSSH shows keys."""
    raw = public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return "SHA256:" + base64.b64encode(hashlib.sha256(raw).digest()).decode().rstrip("=")


def check_name(name: str) -> str:
    if not _NAME.fullmatch(name):
        raise SigningError(f"key name {name!r}: 1 to 32 of a-z 0-9 _ -, starting with a letter")
    return name


def new_key_pair(directory: Path, name: str) -> tuple[Path, Path]:
    """Write NAME.key (0600, created exclusively: an existing key is never overwritten) and
    NAME.pub into `directory` (made 0700)."""
    check_name(name)
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    private_path, public_path = directory / f"{name}.key", directory / f"{name}.pub"
    if private_path.exists() or public_path.exists():
        raise SigningError(f"{private_path} or {public_path} exists already; a key is never "
                           "replaced (remove it first, and tell the PLCs that trusted it)")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    fd = os.open(private_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as out:
        out.write(pem)
    public_path.write_bytes(key.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    return private_path, public_path


def load_private(path: Path) -> Ed25519PrivateKey:
    """An engineer's private key; refused when others may read it (as ssh refuses)."""
    try:
        if stat.S_IMODE(path.stat().st_mode) & 0o077:
            raise SigningError(f"{path} is readable by others: chmod 600 it (a key others can "
                               "read signs for them too)")
        key = serialization.load_pem_private_key(path.read_bytes(), password=None)
    except OSError as exc:
        raise SigningError(f"{path}: {exc.strerror or exc}") from None
    except (ValueError, TypeError) as exc:
        raise SigningError(f"{path}: not an unencrypted PEM private key ({exc})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SigningError(f"{path}: not an Ed25519 key (softplc keys new makes one)")
    return key


def load_public(path: Path) -> Ed25519PublicKey:
    try:
        key = serialization.load_pem_public_key(path.read_bytes())
    except OSError as exc:
        raise SigningError(f"{path}: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise SigningError(f"{path}: not a PEM public key ({exc})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise SigningError(f"{path}: not an Ed25519 public key")
    return key


def message(body: bytes, version: int | None) -> bytes:
    """What is signed: the bytes behind the context, and the version when there is one."""
    if version is None:
        return CONTEXT + body
    return CONTEXT_VERSIONED + f"version {version}\n".encode() + body


def sign(body: bytes, key: Ed25519PrivateKey, version: int | None = None) -> str:
    """The signature line of `body`, the exact bytes a download will carry; `version` (a
    whole number, 0 to MAX_VERSION) is signed with them. None: an unversioned line, which a
    PLC takes as version 0."""
    if version is not None and not 0 <= version <= MAX_VERSION:
        raise SigningError(f"version {version}: a whole number from 0 to {MAX_VERSION}")
    signature = base64.b64encode(key.sign(message(body, version))).decode()
    line = f"{ALGORITHM} {fingerprint(key.public_key())} {signature}"
    return line if version is None else f"{line} version={version}"


@dataclass(frozen=True, slots=True)
class Signature:
    key_id: str
    raw: bytes
    version: int | None = None  # None: an unversioned line (version 0)

    @classmethod
    def parse(cls, line: str) -> Signature:
        match = _LINE.fullmatch(line.strip())
        if match is None:
            raise SigningError("not a softplc signature (expected one line "
                               "'ed25519 SHA256:KEY BASE64 [version=N]', as softplc sign "
                               "writes)")
        try:
            raw = base64.b64decode(match.group(2), validate=True)
        except binascii.Error as exc:
            raise SigningError(f"signature not base64 ({exc})") from None
        version = match.group(3)
        return cls(match.group(1), raw, None if version is None else int(version))


@dataclass(frozen=True, slots=True)
class Signed:
    """Who signed a body, and the version signed with it (0: an unversioned signature)."""

    signer: str
    version: int


@dataclass(frozen=True, slots=True)
class TrustedKeys:
    """The public keys a PLC takes programs from, by name (the file's stem: `alice.pub` is
    alice). Empty: signatures are not asked for (and not checked)."""

    keys: tuple[tuple[str, str, Ed25519PublicKey], ...] = ()  # name, fingerprint, key
    problems: tuple[str, ...] = ()  # files skipped, one line each

    @classmethod
    def load(cls, directory: Path) -> TrustedKeys:
        keys, problems = [], []
        try:
            paths = sorted(directory.glob("*.pub"))[:MAX_KEYS]
        except OSError:
            paths = []
        for path in paths:
            try:
                key = load_public(path)
            except SigningError as exc:
                problems.append(str(exc))
                continue
            keys.append((path.stem, fingerprint(key), key))
        return cls(tuple(keys), tuple(problems))

    @property
    def names(self) -> list[str]:
        return [name for name, _, _ in self.keys]

    def verify(self, body: bytes, line: str | None) -> Signed:
        """The trusted key that signed `body` and the version signed with it;
        SignatureRefused otherwise."""
        trusted = f"(trusted: {', '.join(self.names)})"
        if not line:
            raise SignatureRefused(f"{DOWNLOAD_REFUSED}: not signed by a trusted key {trusted}")
        try:
            signature = Signature.parse(line)
        except SigningError as exc:
            raise SignatureRefused(f"{DOWNLOAD_REFUSED}: unreadable signature: {exc}") from None
        for name, key_id, key in self.keys:
            if key_id != signature.key_id:
                continue
            try:
                key.verify(signature.raw, message(body, signature.version))
            except InvalidSignature:
                raise SignatureRefused(
                    f"{DOWNLOAD_REFUSED}: the signature by {name} does not match the bytes "
                    "sent (changed after signing, its version edited, or signed for another "
                    "program)") from None
            return Signed(name, signature.version or 0)
        raise SignatureRefused(f"{DOWNLOAD_REFUSED}: signed by key {signature.key_id}, which "
                               f"this PLC does not trust {trusted}")
