"""The security files of a state directory, checked once before `softplc run` starts its
services (issue 38, item 4): each one that is corrupt, truncated or unreadable gives one line
naming the file, what is wrong and what to do.

Owns: which files are read (the owner's key, the users file, the trusted keys and the signed
version of the running program, the API's and the OPC UA server's certificates and keys, the
Modbus/TCP Security ones, the trust lists of client certificates, the audit trail) and which
problems refuse the start (a file a service needs to start at all: the owner's key, the OPC
UA server's key) and which start the service closed with a warning (nobody but the owner
logs in, every download refused, ...). Expired certificates and key files others may read
are named here too.
Does not know: processes, asyncua, aiohttp; how each service uses the files.
"""

from __future__ import annotations

import datetime
import stat
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from cryptography import x509
from cryptography.hazmat.primitives import serialization

from softplc.security import auth, versions
from softplc.security.audit import AuditTrail
from softplc.security.settings import SecuritySettings
from softplc.security.signing import TrustedKeys
from softplc.security.trust import PKI_DIR
from softplc.security.users import UserError, UserStore

OPCUA_OWN: Final = Path(PKI_DIR) / "own"
MODBUS_TLS: Final = Path("modbus-tls") / "tls"


@dataclass
class Findings:
    refused: list[str] = field(default_factory=list)  # the start is refused: one line each
    warnings: list[str] = field(default_factory=list)  # the service starts closed


def check(state_dir: Path, settings: SecuritySettings, *, opcua: bool = False) -> Findings:
    """Every security file of `state_dir` that exists (a missing one is made at start)."""
    state_dir = Path(state_dir)
    found = Findings()
    _token(state_dir / auth.TOKEN_FILE, found)
    _users(state_dir, found)
    _trusted_keys(settings, state_dir, found)
    if (problem := versions.read(state_dir).problem) is not None:
        found.warnings.append(problem)
    if opcua:
        _key(state_dir / OPCUA_OWN / "key.pem", found, "the OPC UA server's key",
             refuse=True, remake=True)
        _certificate(state_dir / OPCUA_OWN / "cert.der", found, "the OPC UA server's "
                     "certificate (made again at start)", refuse=False)
    for trusted in (state_dir / PKI_DIR / "trusted", state_dir / "modbus-tls" / "trusted"):
        for path in sorted(trusted.glob("*.der")) if trusted.is_dir() else []:
            _certificate(path, found, "a trusted client certificate (it trusts nobody: "
                         "remove it, and accept the client's certificate again)", refuse=False)
    for cert, key, what in _tls_pairs(state_dir, settings):
        _certificate(cert, found, what, refuse=False)
        _key(key, found, f"the key of {what}", refuse=False, remake=False)
    _audit(state_dir, found)
    return found


def _token(path: Path, found: Findings) -> None:
    if not path.exists():
        return
    try:
        auth.read_token(path)
    except (auth.TokenFileError, OSError) as exc:
        found.refused.append(f"{exc}")


def _users(state_dir: Path, found: Findings) -> None:
    try:
        UserStore(state_dir).users()
    except UserError as exc:
        found.warnings.append(f"{exc}: fix it or remove it (softplc users add makes a new "
                              "one); the services start, and only the owner's key gets in")


def _trusted_keys(settings: SecuritySettings, state_dir: Path, found: Findings) -> None:
    directory = settings.trusted_dir(state_dir)
    keys = TrustedKeys.load(directory)
    found.warnings += [f"trusted key skipped: {problem}" for problem in keys.problems]
    if settings.trusted_keys is not None and not keys.keys:
        found.warnings.append(f"--trusted-keys {directory}: no usable key there: every "
                              "download is refused until one is trusted (softplc keys trust)")


def _key(path: Path, found: Findings, what: str, *, refuse: bool, remake: bool) -> None:
    try:
        data = path.read_bytes()
        serialization.load_pem_private_key(data, password=None)
    except FileNotFoundError:
        return
    except (OSError, ValueError, TypeError) as exc:
        todo = "remove it to get a new one at start (clients that trusted the old " \
            "certificate must trust the new one)" if remake else "replace it"
        line = f"{path}: {what} cannot be used ({_why(exc)}); {todo}"
        (found.refused if refuse else found.warnings).append(line)
        return
    if stat.S_IMODE(path.stat().st_mode) & 0o077:
        found.warnings.append(f"{path}: {what} is readable by others (mode "
                              f"{stat.S_IMODE(path.stat().st_mode):04o}); chmod 600 it")


def _certificate(path: Path, found: Findings, what: str, *, refuse: bool) -> None:
    try:
        data = path.read_bytes()
        cert = x509.load_der_x509_certificate(data) if path.suffix == ".der" else \
            x509.load_pem_x509_certificate(data)
    except FileNotFoundError:
        return
    except (OSError, ValueError) as exc:
        line = f"{path}: {what} cannot be read ({_why(exc)})"
        (found.refused if refuse else found.warnings).append(line)
        return
    now = datetime.datetime.now(datetime.UTC)
    if cert.not_valid_after_utc < now:
        found.warnings.append(f"{path}: {what} expired on "
                              f"{cert.not_valid_after_utc:%Y-%m-%d}; clients will refuse it: "
                              "replace it (or remove a certificate softplc made, for a new one)")


def _tls_pairs(state_dir: Path, settings: SecuritySettings) -> Iterator[tuple[Path, Path, str]]:
    tls = settings.tls
    if tls.cert and tls.key:
        yield Path(tls.cert), Path(tls.key), "the API's certificate (--tls-cert)"
    else:
        yield state_dir / "tls" / "cert.pem", state_dir / "tls" / "key.pem", \
            "the API's certificate"
    yield state_dir / MODBUS_TLS / "cert.pem", state_dir / MODBUS_TLS / "key.pem", \
        "the Modbus/TCP Security certificate"


def _audit(state_dir: Path, found: Findings) -> None:
    try:
        verdict = AuditTrail(state_dir).verify()
    except (OSError, ValueError) as exc:
        found.warnings.append(f"{state_dir}/audit.jsonl: the audit trail cannot be read "
                              f"({_why(exc)}); records are still appended")
        return
    if not verdict.ok:
        found.warnings.append(f"the audit trail in {state_dir} is broken at {verdict.where}: "
                              f"{verdict.problem} (softplc audit --verify --state-dir "
                              f"{state_dir})")


def _why(exc: BaseException) -> str:
    text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
    text = text.split(" See https://")[0]  # cryptography's FAQ link: not what to do here
    return text.splitlines()[0][:120] if text else type(exc).__name__
