"""The API's bearer token: when it is required, where it lives, how a request proves it.

Owns: the loopback rule, the token file (state_dir/api_token, mode 0600, created once with
secrets.token_urlsafe and reused), the constant-time check of an Authorization header, and
where a client finds its token (argument, SOFTPLC_API_TOKEN, a state dir).
Does not know: HTTP routing, aiohttp, the PLC. It never logs or formats a token.
"""

from __future__ import annotations

import hmac
import ipaddress
import os
import secrets
import stat
from pathlib import Path
from typing import Final
from urllib.parse import urlsplit

from softplc.core.errors import SoftplcError

TOKEN_FILE: Final = "api_token"
TOKEN_ENV: Final = "SOFTPLC_API_TOKEN"
_TOKEN_BYTES: Final = 32  # 256 bits, 43 URL-safe characters


class TokenFileError(SoftplcError, OSError):
    """The token file exists but cannot be used (unreadable, empty, not a regular file)."""


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and "localhost". A wildcard ("", 0.0.0.0, ::) or any other
    name is not: it may be reachable from another machine."""
    name = host.strip().strip("[]").lower()
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def token_required(host: str, required: bool | None) -> bool:
    """An explicit choice wins; otherwise a token guards every non-loopback bind."""
    return (not is_loopback(host)) if required is None else required


def host_header_is_loopback(host_header: str | None) -> bool:
    """Whether a request's Host header names a loopback host. A service without a token
    refuses other names: a browser page on another site can otherwise reach it through
    DNS rebinding. No header (HTTP/1.0) comes from no browser and is accepted."""
    if not host_header:
        return True
    hostname = urlsplit("//" + host_header).hostname
    return hostname is not None and is_loopback(hostname)


def same_origin(origin: str | None, host_header: str | None) -> bool:
    """Whether a browser's Origin header (absent for non-browser clients) is the service
    itself: a cross-site page must not drive the PLC with a simple POST (CSRF)."""
    if origin is None:
        return True
    netloc = urlsplit(origin).netloc.lower()
    return bool(netloc) and netloc == (host_header or "").lower()


def load_or_create_token(state_dir: Path) -> str:
    """The token in `state_dir/api_token`; created (mode 0600) on first use, reused after.
    A file left readable by others is tightened to 0600 before it is used."""
    state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    path = state_dir / TOKEN_FILE
    token = "-"
    while token.startswith("-"):  # `--token -x...` would read as an option
        token = secrets.token_urlsafe(_TOKEN_BYTES)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    except FileExistsError:
        return _read_token(path)
    with os.fdopen(fd, "w", encoding="ascii") as handle:
        handle.write(token + "\n")
    return token


def _read_token(path: Path) -> str:
    info = path.lstat()
    if not stat.S_ISREG(info.st_mode):
        raise TokenFileError(f"{path} is not a regular file; remove it to get a new token")
    if stat.S_IMODE(info.st_mode) & 0o077:
        path.chmod(0o600)
    token = path.read_text(encoding="ascii").strip()
    if not token:
        raise TokenFileError(f"{path} is empty; remove it to get a new token")
    return token


def bearer_matches(header: str | None, token: str) -> bool:
    """Whether an Authorization header carries `token` (constant-time comparison)."""
    if not header:
        return False
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer":
        return False
    return hmac.compare_digest(given.strip().encode(), token.encode())


def client_token(token: str | None = None, state_dir: Path | str | None = None) -> str | None:
    """Where a client finds its token: the argument, then $SOFTPLC_API_TOKEN, then the
    api_token file of the server's state dir (same machine). None when there is none."""
    if token:
        return token
    from_env = os.environ.get(TOKEN_ENV, "").strip()
    if from_env:
        return from_env
    if state_dir is not None:
        path = Path(state_dir) / TOKEN_FILE
        if path.is_file():
            return path.read_text(encoding="ascii").strip() or None
    return None
