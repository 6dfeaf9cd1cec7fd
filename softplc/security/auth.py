"""The owner's key and the loopback rules: where the key lives and how a client finds it.

Owns: the loopback rule, the owner's key file (state_dir/api_token, mode 0600, created once
with secrets.token_urlsafe and reused: the built-in admin of the account that owns the state
directory), the constant-time check of a bearer header, the per-account index of local
servers (which state directory serves which loopback port, so that the owner's CLI finds
its key by the URL alone), and where a client finds its token (argument,
SOFTPLC_API_TOKEN, a state dir, the index).
Does not know: HTTP routing, aiohttp, users and roles, the PLC. It never logs or formats a
token.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import re
import stat
import tempfile
from pathlib import Path
from urllib.parse import urlsplit

from softplc.core.errors import SoftplcError

TYPE_CHECKING = False  # a client command (issue 40) imports neither typing nor the
if TYPE_CHECKING:  # server's hmac and secrets: those are imported where used
    from typing import Final

TOKEN_FILE: Final = "api_token"
TOKEN_ENV: Final = "SOFTPLC_API_TOKEN"
INDEX_ENV: Final = "SOFTPLC_RUNTIME_DIR"  # where the index of local servers is (tests)
_TOKEN_BYTES: Final = 32  # 256 bits, 43 URL-safe characters
_TOKEN_TEXT: Final = re.compile(r"[A-Za-z0-9_\-.~+/=]{16,512}")


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


def same_origin(origin: str | None, host_header: str | None, scheme: str = "http") -> bool:
    """Whether a browser's Origin header (absent for non-browser clients) is the service
    itself, scheme included: a cross-site page must not drive the PLC with a simple POST
    (CSRF), nor a page served over plain HTTP drive the HTTPS service under the same host
    name (its scripts are anybody's on the way)."""
    if origin is None:
        return True
    parts = urlsplit(origin)
    netloc = parts.netloc.lower()
    return bool(netloc) and netloc == (host_header or "").lower() and \
        parts.scheme.lower() == scheme


def load_or_create_token(state_dir: Path) -> str:
    """The token in `state_dir/api_token`; created (mode 0600) on first use, reused after.
    A file left readable by others is tightened to 0600 before it is used."""
    state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    path = state_dir / TOKEN_FILE
    import secrets

    token = "-"
    while token.startswith("-"):  # `--token -x...` would read as an option
        token = secrets.token_urlsafe(_TOKEN_BYTES)
    # Written aside, then linked into place: a process starting at the same moment (the
    # OPC UA one) reads the whole token or makes its own, never an empty file.
    fd, tmp = tempfile.mkstemp(dir=state_dir, prefix=".api_token.")
    try:
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            handle.write(token + "\n")
        os.link(tmp, path)
    except FileExistsError:
        return read_token(path)
    finally:
        os.unlink(tmp)
    return token


def read_token(path: Path) -> str:
    """The owner's key in `path`; TokenFileError (one line: the file, what is wrong, what to
    do) when it is no usable key: a garbled key would be a password nobody knows."""
    info = path.lstat()
    if not stat.S_ISREG(info.st_mode):
        raise TokenFileError(f"{path} is not a regular file; remove it to get a new token")
    if stat.S_IMODE(info.st_mode) & 0o077:
        path.chmod(0o600)
    try:
        token = path.read_bytes().decode("ascii").strip()
    except UnicodeDecodeError:
        raise TokenFileError(f"{path} is not a softplc key (not ASCII text); remove it to get "
                             "a new one (clients holding the old key need the new one)") from None
    if not token:
        raise TokenFileError(f"{path} is empty; remove it to get a new token")
    if not _TOKEN_TEXT.fullmatch(token):
        raise TokenFileError(f"{path} is not a softplc key (one line of letters, digits, - "
                             "and _ expected); remove it to get a new one (clients holding "
                             "the old key need the new one)")
    return token


def bearer_matches(header: str | None, token: str) -> bool:
    """Whether an Authorization header carries `token` (constant-time comparison)."""
    if not header:
        return False
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer":
        return False
    import hmac

    return hmac.compare_digest(given.strip().encode(), token.encode())


def client_token(token: str | None = None, state_dir: Path | str | None = None,
                 url: str | None = None) -> str | None:
    """Where a client finds its token: the argument, then $SOFTPLC_API_TOKEN, then the
    api_token file of the server's state dir (same machine), then, for a loopback `url`, the
    state dir that this account's index says serves it. None when there is none."""
    if token:
        return token
    from_env = os.environ.get(TOKEN_ENV, "").strip()
    if from_env:
        return from_env
    if state_dir is None and url is not None:
        state_dir = indexed_state_dir(url)
    if state_dir is not None:
        path = Path(state_dir) / TOKEN_FILE
        with contextlib.suppress(OSError, UnicodeDecodeError):  # not ours to read: none
            return path.read_text(encoding="ascii").strip() or None
    return None


# -- the index of this account's local servers ---------------------------------------------
# One file per loopback port in a directory only this account can use (as tmux and
# ssh-agent keep their sockets): {"pid", "state_dir"}. It holds no secret: the key stays in
# the state directory, readable by its owner only. An entry whose process is gone, or
# belongs to another account, is ignored.

def index_dir(create: bool = False) -> Path | None:
    """This account's index directory (made 0700 when `create`: a server registering; a
    client's look-up leaves nothing behind); None when there is none or it cannot be
    trusted (not a directory of ours, open to others)."""
    base = os.environ.get(INDEX_ENV) or os.environ.get("XDG_RUNTIME_DIR") \
        or tempfile.gettempdir()
    path = Path(base) / f"softplc-{os.geteuid()}"
    if create:
        with contextlib.suppress(FileExistsError, OSError):
            path.mkdir(mode=0o700, parents=True)
    try:
        info = path.lstat()
    except OSError:
        return None
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.geteuid() \
            or stat.S_IMODE(info.st_mode) & 0o077:
        return None
    return path


def register_server(port: int, state_dir: Path) -> Path | None:
    """Say that this process serves loopback `port` from `state_dir`; the entry's path."""
    directory = index_dir(create=True)
    if directory is None:
        return None
    entry = directory / f"api-{port}.json"
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=".api-")
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        json.dump({"pid": os.getpid(), "state_dir": str(state_dir.resolve())}, handle)
    os.replace(tmp, entry)
    return entry


def unregister_server(entry: Path | None) -> None:
    """Remove the entry if it is still this process's (a newer server may own the port)."""
    if entry is None:
        return
    with contextlib.suppress(OSError, ValueError):
        if json.loads(entry.read_text(encoding="utf-8")).get("pid") == os.getpid():
            entry.unlink()
            entry.parent.rmdir()  # the last server of this account: nothing left in /tmp


def indexed_state_dir(url: str) -> Path | None:
    """The state dir of the live server of this account at a loopback `url`, if indexed."""
    parts = urlsplit(url)
    if parts.hostname is None or not is_loopback(parts.hostname):
        return None
    directory = index_dir()
    try:
        port = parts.port or (443 if parts.scheme == "https" else 80)
        entry = json.loads((directory / f"api-{port}.json").read_text(encoding="utf-8")) \
            if directory is not None else None
        if not isinstance(entry, dict):
            return None
        os.kill(int(entry["pid"]), 0)  # gone: ProcessLookupError; another's: PermissionError
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return Path(str(entry["state_dir"]))
