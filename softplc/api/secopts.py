"""`softplc run`'s security options: HTTPS (--tls, --tls-cert, --tls-key) and the keys whose
signatures downloads need (--trusted-keys).

Owns: registering them on the run parser, checking them at start (one line per problem), and
handing them to the services (security/settings.py: STATE_DIR/security.json).
Does not know: certificates (tls.py), signatures (security/signing.py), processes.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from softplc.security.settings import TRUSTED_DIR, SecuritySettings, load, save
from softplc.security.tls import (
    MODES,
    TlsError,
    TlsSettings,
    certificate,
    fingerprint,
    server_context,
)

__all__ = ["TRUSTED_DIR", "SecuritySettings", "add_run_options", "load", "prepare", "save"]

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
    (http or https), `args.api_tls` (the certificate in words) and `args.api_cert` (its
    absolute path, "" without TLS) for the banner."""
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
    args.api_scheme, args.api_tls, args.api_cert = "http", "", ""
    try:
        if api and tls.wanted(api[0]):  # made and checked here: a bad file stops the start
            cert_path, key_path, made = certificate(tls, Path(args.state_dir), api[0])
            server_context(cert_path, key_path)
            args.api_scheme, args.api_cert = "https", str(cert_path.resolve())
            args.api_tls = (f"{'new ' if made else ''}certificate {cert_path}, SHA-256 "
                            f"{fingerprint(cert_path)}")
        save(Path(args.state_dir), settings)
    except TlsError as exc:
        return str(exc)
    except (OSError, ValueError) as exc:
        return f"TLS or security settings in {args.state_dir}: {exc}"
    return None


def _absolute(path: str | None) -> str | None:
    return str(Path(path).resolve()) if path else None
