"""What a door remembers of identities it proved, so that a password costs scrypt once: the
verified user:password pairs (HTTP Basic, OPC UA user-name tokens) and the page's sessions.

Owns: both tables, bounded and timed (the least recent go first), keyed by a salted SHA-256
(a pepper of this process: the tables hold no password, nor a session's secret), and the rule
that an entry is only as good as its identity is *now* (security/decide.py's Authority: an
entry whose user was removed, or whose password changed, is dropped when found).
Does not know: HTTP, OPC UA, cookies, back-off.
"""

from __future__ import annotations

import hashlib
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Final

from softplc.security.decide import Authority, Identity

PAIRS_KEPT: Final = 64  # verified name:password pairs: a script or a reconnecting client
PAIRS_S: Final = 300.0  # pays scrypt once in 5 minutes
SESSIONS_KEPT: Final = 256
SESSION_S: Final = 8 * 3600.0  # a shift


class Remembered:
    """One table of identities by a secret (a name:password pair, a session's token)."""

    def __init__(self, authority: Authority, kept: int, lifetime_s: float,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._authority = authority
        self._kept, self._lifetime_s, self._clock = kept, lifetime_s, clock
        self._pepper = secrets.token_bytes(32)
        self._table: OrderedDict[bytes, tuple[Identity, float]] = OrderedDict()

    def _key(self, secret: str) -> bytes:
        return hashlib.sha256(self._pepper + secret.encode("utf-8", "surrogatepass")).digest()

    def keep(self, secret: str, who: Identity) -> None:
        self._table[self._key(secret)] = (who, self._clock() + self._lifetime_s)
        while len(self._table) > self._kept:
            self._table.popitem(last=False)

    def find(self, secret: str) -> Identity | None:
        """The identity kept under `secret` while it lives and still holds a role now."""
        key = self._key(secret)
        entry = self._table.get(key)
        if entry is None:
            return None
        if entry[1] < self._clock() or self._authority.role_now(entry[0])[0] is None:
            del self._table[key]
            return None
        self._table.move_to_end(key)
        return entry[0]

    def forget(self, secret: str) -> Identity | None:
        entry = self._table.pop(self._key(secret), None)
        return entry[0] if entry else None


def pair(name: str, password: str) -> str:
    return f"{name}\0{password}"


def new_session() -> str:
    return secrets.token_urlsafe(32)
