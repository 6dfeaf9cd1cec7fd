"""Named users: their roles, password hashes and API keys, kept in STATE_DIR/users.

Owns: the file (JSON, mode 0600, replaced atomically under STATE_DIR/users.lock), password
hashing (scrypt, parameters in each hash), API keys (random, only their SHA-256 stored),
and the pure checks `verify(name, password)` and `verify_key(key)` that every interface
(HTTP now, OPC UA user tokens next) asks. The file is read again when it changes on disk,
so `softplc users ...` acts on a running PLC at once.
Does not know: HTTP, back-off, the audit trail, the terminal.
"""

from __future__ import annotations

import base64
import contextlib
import fcntl
import hashlib
import hmac
import json
import os
import re
import secrets
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from softplc.core.errors import SoftplcError
from softplc.security.files import write_private
from softplc.security.roles import Role

USERS_FILE: Final = "users"
OWNER: Final = "owner"  # the built-in user of STATE_DIR/api_token: reserved
# scrypt: 2**15 x 8 x 128 bytes = 32 MiB per hash, p = 3 (OWASP's password storage cheat
# sheet lists N=2^15, r=8, p=3 as one of its equal-strength choices); measured on the 2-core
# test machine under load: about 0.3 s. Kept in each hash: raising them later re-hashes
# nobody, old hashes still verify.
SCRYPT_LOG_N: Final = 15
SCRYPT_R: Final = 8
SCRYPT_P: Final = 3
_SALT_BYTES: Final = 16
_HASH_BYTES: Final = 32
_MAXMEM: Final = 256 << 20
_KEY_BYTES: Final = 32  # 256 bits
_NAME: Final = re.compile(r"[a-z][a-z0-9_-]{0,31}")
MIN_PASSWORD: Final = 8
MAX_PASSWORD: Final = 1024


class UserError(SoftplcError, ValueError):
    """A user command that cannot be done (unknown user, bad name, short password, ...)."""


@dataclass(frozen=True, slots=True)
class User:
    name: str
    role: Role
    password: str  # "$scrypt$ln=15,r=8,p=3$SALT$HASH" (base64), never the password
    key_sha256: str | None = None
    created: str = ""

    def as_json(self) -> dict[str, Any]:
        return {"role": self.role.label, "password": self.password, "key": self.key_sha256,
                "created": self.created}


def check_name(name: str) -> str:
    if not _NAME.fullmatch(name):
        raise UserError(f"user name {name!r}: 1 to 32 of a-z 0-9 _ -, starting with a letter")
    if name == OWNER:
        raise UserError(f"{OWNER!r} is the built-in user of STATE_DIR/api_token")
    return name


def hash_password(password: str, log_n: int = SCRYPT_LOG_N) -> str:
    if not MIN_PASSWORD <= len(password) <= MAX_PASSWORD:
        raise UserError(f"a password has {MIN_PASSWORD} to {MAX_PASSWORD} characters")
    salt = secrets.token_bytes(_SALT_BYTES)
    digest = _scrypt(password, salt, log_n, SCRYPT_R, SCRYPT_P)
    return (f"$scrypt$ln={log_n},r={SCRYPT_R},p={SCRYPT_P}${_b64(salt)}${_b64(digest)}")


def password_matches(password: str, stored: str) -> bool:
    """Whether `password` is the one `stored` was made from (constant-time comparison)."""
    try:
        _, kind, params, salt, digest = stored.split("$")
        values = dict(item.split("=") for item in params.split(","))
        log_n, r, p = int(values["ln"]), int(values["r"]), int(values["p"])
        expected = base64.b64decode(digest)
        if kind != "scrypt" or not (10 <= log_n <= 20 and 1 <= r <= 32 and 1 <= p <= 16):
            return False
        got = _scrypt(password, base64.b64decode(salt), log_n, r, p, len(expected))
    except (ValueError, KeyError):
        return False
    return hmac.compare_digest(got, expected)


def _scrypt(password: str, salt: bytes, log_n: int, r: int, p: int,
            length: int = _HASH_BYTES) -> bytes:
    return hashlib.scrypt(password.encode("utf-8")[:MAX_PASSWORD * 4], salt=salt, n=1 << log_n,
                          r=r, p=p, maxmem=_MAXMEM, dklen=length)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def key_digest(secret: str) -> str:
    """API keys are 256 random bits: a plain SHA-256 keeps them unusable if the file leaks
    (a slow hash guards guessable secrets, which keys are not)."""
    return hashlib.sha256(secret.encode("utf-8")).hexdigest()


class UserStore:
    """STATE_DIR/users. Reads are cached by the file's (inode, size, mtime)."""

    def __init__(self, state_dir: Path | str) -> None:
        self.path = Path(state_dir) / USERS_FILE
        self._seen: tuple[int, int, int] | None = None
        self._users: dict[str, User] = {}
        self._unusable = ""  # why the file as last seen cannot be used ("" when it can)

    # -- the checks every interface asks ------------------------------------------------------

    def verify(self, name: str, password: str) -> Role | None:
        """The role of `name` when `password` is theirs, else None. Blocking (scrypt)."""
        user = self.users().get(name)
        if user is None:
            password_matches(password, _DUMMY)  # the same cost: no user enumeration by time
            return None
        return user.role if password_matches(password, user.password) else None

    def verify_key(self, key: str) -> User | None:
        """The user whose API key (`NAME.SECRET`) this is, else None."""
        name, dot, secret = key.partition(".")
        user = self.users().get(name) if dot else None
        if user is None or user.key_sha256 is None:
            return None
        return user if hmac.compare_digest(key_digest(secret), user.key_sha256) else None

    def users(self) -> dict[str, User]:
        try:
            info = self.path.stat()
        except FileNotFoundError:
            self._seen, self._users, self._unusable = None, {}, ""
            return self._users
        seen = (info.st_ino, info.st_size, info.st_mtime_ns)
        if seen != self._seen:  # an unusable file too is read again only when it changed
            try:
                self._users, self._unusable = self._load(), ""
            except UserError as exc:
                self._users, self._unusable = {}, str(exc)
            self._seen = seen
        if self._unusable:
            raise UserError(self._unusable)
        return self._users

    def _load(self) -> dict[str, User]:
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            return {name: User(name, Role.parse(entry["role"]), str(entry["password"]),
                               entry.get("key"), str(entry.get("created", "")))
                    for name, entry in data["users"].items()}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise UserError(f"{self.path} is unusable ({exc}); nobody can log in") from None

    # -- changes (softplc users ...) ------------------------------------------------------------

    def add(self, name: str, role: Role, password: str) -> User:
        check_name(name)
        hashed = hash_password(password)
        with self._changing() as users:
            if name in users:
                raise UserError(f"user {name!r} exists (softplc users passwd or remove)")
            users[name] = User(name, role, hashed,
                               created=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()))
            return users[name]

    def set_password(self, name: str, password: str) -> None:
        hashed = hash_password(password)
        with self._changing() as users:
            user = self._known(users, name)
            users[name] = User(name, user.role, hashed, user.key_sha256, user.created)

    def set_role(self, name: str, role: Role) -> None:
        with self._changing() as users:
            user = self._known(users, name)
            users[name] = User(name, role, user.password, user.key_sha256, user.created)

    def new_key(self, name: str) -> str:
        """A new API key for `name` (the old one stops working); shown once, stored hashed."""
        secret = secrets.token_urlsafe(_KEY_BYTES)
        with self._changing() as users:
            user = self._known(users, name)
            users[name] = User(name, user.role, user.password, key_digest(secret), user.created)
        return f"{name}.{secret}"

    def revoke_key(self, name: str) -> None:
        with self._changing() as users:
            user = self._known(users, name)
            users[name] = User(name, user.role, user.password, None, user.created)

    def remove(self, name: str) -> None:
        with self._changing() as users:
            self._known(users, name)
            del users[name]

    @staticmethod
    def _known(users: dict[str, User], name: str) -> User:
        if name not in users:
            raise UserError(f"no user {name!r} (softplc users list)")
        return users[name]

    @contextlib.contextmanager
    def _changing(self) -> Iterator[dict[str, User]]:
        """Read, change and replace the file under an exclusive lock: two commands at once
        never lose one another's change."""
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        lock = os.open(self.path.with_name(USERS_FILE + ".lock"), os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
            self._seen = None
            users = dict(self.users())
            yield users
            self._write(users)
        finally:
            os.close(lock)

    def _write(self, users: dict[str, User]) -> None:
        text = json.dumps({"format": 1, "users": {n: u.as_json() for n, u in
                                                  sorted(users.items())}}, indent=1)
        write_private(self.path, (text + "\n").encode("utf-8"), sync_directory=True)
        self._seen = None


# A hash of nothing anyone knows, verified for unknown names so that they cost the same.
_DUMMY: Final = (f"$scrypt$ln={SCRYPT_LOG_N},r={SCRYPT_R},p={SCRYPT_P}$"
                 "c29mdHBsYy1kdW1teS1zYWx0$" + _b64(bytes(_HASH_BYTES)))
