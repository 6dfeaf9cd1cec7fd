"""`softplc run`'s security options: HTTPS (--tls, --tls-cert, --tls-key) and the keys whose
signatures downloads need (--trusted-keys).

Owns: registering them on the run parser, checking them at start (one line per problem), and
handing them to the HTTP service: the supervisor starts it in another process from a
configuration that has no room for them, so `softplc run` writes them to
STATE_DIR/security.json at every start and the service reads them there (absent: plain HTTP
and STATE_DIR/trusted_keys, as for a service started on its own).
Does not know: certificates (tls.py), signatures (security/signing.py), processes.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from softplc.security.tls import (
    MODES,
    Mode,
    TlsError,
    TlsSettings,
    certificate,
    fingerprint,
    server_context,
)

SETTINGS_FILE: Final = "security.json"
TRUSTED_DIR: Final = "trusted_keys"  # in the state directory, unless --trusted-keys


@dataclass(frozen=True, slots=True)
class SecuritySettings:
    tls: TlsSettings = field(default_factory=TlsSettings)
    trusted_keys: str | None = None  # None: STATE_DIR/trusted_keys

    def trusted_dir(self, state_dir: Path) -> Path:
        return Path(self.trusted_keys) if self.trusted_keys else Path(state_dir) / TRUSTED_DIR


def add_run_options(run: argparse.ArgumentParser) -> None:
    run.add_argument("--tls", choices=MODES, default="auto",
                     help="HTTPS for the API: on, off, or auto: off on a loopback --api, on "
                     "elsewhere; the certificate is --tls-cert, else one made at the first start "
                     "in STATE_DIR/tls/ (default: %(default)s)")
    run.add_argument("--tls-cert", metavar="FILE", help="the API's certificate (PEM, with its "
                     "chain), with --tls-key (default: STATE_DIR/tls/cert.pem, made when missing)")
    run.add_argument("--tls-key", metavar="FILE", help="the key of --tls-cert (PEM)")
    run.add_argument("--modbus-tls", type=_modbus_tls, default=None, metavar="HOST:PORT|off",
                     help="Modbus/TCP Security: TLS with client certificates whose role decides "
                     "writes, on HOST:PORT (802 is its port; below 1024 needs root or "
                     "CAP_NET_BIND_SERVICE), or off (default: off; docs/modbus.md)")
    run.add_argument("--trusted-keys", metavar="DIR", help="downloads must be signed by one of "
                     "the Ed25519 public keys DIR/*.pub (softplc keys, softplc sign); none there: "
                     f"unsigned downloads are taken (default: STATE_DIR/{TRUSTED_DIR})")


def _modbus_tls(text: str) -> tuple[str, int] | None:
    if text in ("off", "none"):
        return None
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT or off, got {text!r}")
    return (host or "127.0.0.1", int(port))


def prepare(args: argparse.Namespace) -> str | None:
    """Check the options, make the certificate when TLS is on and none is there, and write
    them for the HTTP service; the first problem as one line, or None. Sets `args.api_scheme`
    (http or https) and `args.api_tls` (the certificate in words) for the banner."""
    cert, key = getattr(args, "tls_cert", None), getattr(args, "tls_key", None)
    if bool(cert) != bool(key):
        return "--tls-cert and --tls-key go together"
    for what, path in (("--tls-cert", cert), ("--tls-key", key)):
        if path and not Path(path).is_file():
            return f"{what} {path}: no such file"
    trusted = getattr(args, "trusted_keys", None)
    if trusted and not Path(trusted).is_dir():
        return f"--trusted-keys {trusted}: no such directory"
    tls = TlsSettings(getattr(args, "tls", "auto"), _absolute(cert), _absolute(key))
    settings = SecuritySettings(tls, _absolute(trusted))
    api = getattr(args, "api", None)
    args.api_scheme, args.api_tls = "http", ""
    try:
        if api and tls.wanted(api[0]):  # made and checked here: a bad file stops the start
            cert_path, key_path, made = certificate(tls, Path(args.state_dir), api[0])
            server_context(cert_path, key_path)
            args.api_scheme = "https"
            args.api_tls = (f"{'new ' if made else ''}certificate {cert_path}, SHA-256 "
                            f"{fingerprint(cert_path)}")
        save(Path(args.state_dir), settings)
    except TlsError as exc:
        return str(exc)
    except (OSError, ValueError) as exc:
        return f"TLS or security settings in {args.state_dir}: {exc}"
    return None


def save(state_dir: Path, settings: SecuritySettings) -> None:
    state_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    data = {"tls": {"mode": settings.tls.mode, "cert": settings.tls.cert,
                    "key": settings.tls.key}, "trusted_keys": settings.trusted_keys}
    fd, tmp = tempfile.mkstemp(dir=state_dir, prefix=f".{SETTINGS_FILE}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            json.dump(data, out)
        os.replace(tmp, state_dir / SETTINGS_FILE)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(state_dir: Path) -> SecuritySettings:
    """What the last `softplc run` on `state_dir` asked for; the defaults without it."""
    try:
        data: Any = json.loads((Path(state_dir) / SETTINGS_FILE).read_text(encoding="utf-8"))
        tls = data["tls"]
        mode: Mode = tls["mode"] if tls["mode"] in MODES else "on"  # edited: the safe side
        return SecuritySettings(TlsSettings(mode, _text(tls.get("cert")), _text(tls.get("key"))),
                                _text(data.get("trusted_keys")))
    except FileNotFoundError:
        return SecuritySettings()
    except (OSError, ValueError, KeyError, TypeError):
        return SecuritySettings(TlsSettings("on"))


def _absolute(path: str | None) -> str | None:
    return str(Path(path).resolve()) if path else None


def _text(value: object) -> str | None:
    return value if isinstance(value, str) and value else None
