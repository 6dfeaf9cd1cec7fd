"""Who sent an HTTP request, whether they may, and the audit record of what they did.

Owns: Principal; reading credentials (a bearer API key `NAME.SECRET`, the owner's key in
STATE_DIR/api_token, HTTP Basic user:password, the page's session cookie), the back-off of
failed logins per user and per peer (a bounded table), the sessions of /login, the rule
"no credentials: the anonymous role" (viewer on loopback, nothing off it), 401/403/429 as
one-line problems, and writing audit records (in a thread: they fsync): a refusal through
refusals.py's rule (the first of a kind at once, its repeats counted per window), anything
else at once; the chain's verdict for status (chainwatch.py).
Does not know: the routes' table (roles.py), the users file's format (users.py), the
trail's format (audit.py), the PLC.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextvars
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from softplc.api.problems import ApiProblem
from softplc.security.audit import AuditTrail
from softplc.security.backoff import Backoff
from softplc.security.chainwatch import ChainWatch
from softplc.security.decide import Authority, Decision, Identity, anonymous
from softplc.security.refusals import RefusalAudit
from softplc.security.remembered import (
    PAIRS_KEPT,
    PAIRS_S,
    SESSION_S,
    SESSIONS_KEPT,
    Remembered,
    new_session,
    pair,
)
from softplc.security.roles import Act, Role
from softplc.security.users import UserStore

log = logging.getLogger(__name__)

COOKIE: Final = "softplc_session"
CHALLENGE: Final = {"WWW-Authenticate": 'Bearer realm="softplc"'}


@dataclass(frozen=True, slots=True)
class Principal:
    """Who a request is from: `user` None when it carried no credentials; `role` (what the
    identity holds now, security/decide.py) None when such a request may do nothing."""

    user: str | None
    role: Role | None
    via: str  # owner, key, basic, session, anonymous
    identity: Identity | None = None  # None: a failed login (audit only)

    def audit(self) -> dict[str, Any]:
        return {"user": self.user, "role": self.role.label if self.role else None,
                "via": self.via}


# Who the guard admitted, for the handler it then runs (the same task): routes and streams
# read it instead of identifying the request again.
PRINCIPAL: Final[contextvars.ContextVar[Principal | None]] = contextvars.ContextVar(
    "softplc_principal", default=None)


class Gate:
    """The credentials check of one API server: the HTTP door of security/decide.py."""

    def __init__(self, state_dir: Path, owner_token: str, anonymous: Role | None,
                 audit: AuditTrail | None = None) -> None:
        self.users = UserStore(state_dir)
        self.authority = Authority(self.users, lambda: self._owner)
        self.audit = audit or AuditTrail(state_dir)
        self.anonymous = anonymous
        self.backoff = Backoff(state_dir=state_dir)
        self.throttled = 0  # logins refused or failed while backing off
        self.anchor: tuple[int, str] | None = None  # the last record this server wrote
        self._owner = owner_token
        self._kdf = asyncio.Semaphore(1)  # one scrypt at a time: 32 MiB and ~0.3 s each
        self._pairs = Remembered(self.authority, PAIRS_KEPT, PAIRS_S)
        self._sessions = Remembered(self.authority, SESSIONS_KEPT, SESSION_S)
        self.watch = ChainWatch(self.audit)
        self.refusals = RefusalAudit(self._append)

    def set_owner(self, token: str) -> None:
        self._owner = token

    def principal(self, who: Identity, via: str | None = None) -> Principal:
        """`who` with the role it holds now."""
        return Principal(who.user, self.authority.role_now(who)[0], via or who.via, who)

    def decide(self, who: Principal, act: Act) -> Decision:
        """The one decision point (security/decide.py) for a request of this door."""
        return self.authority.decide(who.identity or anonymous(None), act)

    async def chain(self) -> dict[str, Any]:
        """The audit chain's verdict for status, at once: the last one computed (`checked_at`),
        checked again in a thread when the trail changed (chainwatch.py)."""
        return {**self.watch.verdict(self.anchor), "throttled_logins": self.throttled}

    async def close(self) -> None:
        """At stop: every refusal still counted written, no further check of the chain."""
        self.watch.close()
        await self.refusals.close()

    def has_credentials(self, request: web.Request) -> bool:
        """An Authorization header (a wrong one is a 401 later), or the cookie of a live
        session. A cookie that names none is no credential: a page of another site, rebound
        to this address (DNS rebinding), sends whatever cookie it set under that name."""
        return "Authorization" in request.headers or \
            self._session(request.cookies.get(COOKIE)) is not None

    async def identify(self, request: web.Request) -> Principal:
        """The request's principal; raises 401 for wrong credentials, 429 while backing off."""
        header = request.headers.get("Authorization")
        if header is None:
            if (found := self._session(request.cookies.get(COOKIE))) is not None:
                return found
            return Principal(None, self.anonymous, "anonymous", anonymous(self.anonymous))
        scheme, _, value = header.strip().partition(" ")
        if scheme.lower() == "bearer":
            return await self._bearer(request, value.strip())
        if scheme.lower() == "basic" and (pair := _basic(value)) is not None:
            return self.principal(await self.password(request, *pair), "basic")
        raise await self.failure(request, None, "credentials neither Bearer nor Basic "
                                   "user:password")

    async def _bearer(self, request: web.Request, token: str) -> Principal:
        who = self.authority.owner(token) or self.authority.by_key(token)
        if who is not None:
            return self.principal(who)
        name = token.partition(".")[0] if "." in token else None
        raise await self.failure(request, name[:32] if name else None, "a wrong API key")

    async def password(self, request: web.Request, name: str, password: str) -> Identity:
        """The identity of `name` if `password` is theirs (Basic and /login): kept for a
        while so that scripts pay scrypt once, but only while the users file still holds the
        hash it was verified with (a changed password is verified again, and fails);
        backing off per user and per peer, every failure audited."""
        keys = (("user", name[:64]), ("peer", request.remote or "?"))
        if (known := self._pairs.find(pair(name, password))) is not None:
            return known
        if (wait_s := self.backoff.wait_s(*keys)) > 0:
            raise await self.throttle(request, name[:32], wait_s)
        async with self._kdf:
            who = await asyncio.to_thread(self.authority.by_password, name, password) \
                if self.authority.known() else None
        if who is None:
            raise await self.failure(request, name[:32], "a wrong user name or password", keys)
        self.backoff.succeeded(*keys)
        self._pairs.keep(pair(name, password), who)
        return who

    async def throttle(self, request: web.Request, name: str, wait_s: float) -> ApiProblem:
        """Audit a login refused unchecked while its user or peer backs off, make its 429."""
        self.throttled += 1
        await self.refused(request, Principal(name, None, "failed"), "login", "refused", 429,
                           {"route": route(request), "reason": "too many failed logins"})
        seconds = max(1, round(wait_s + 0.5))
        return ApiProblem(429, f"too many failed logins: try again in {seconds} s",
                          headers={"Retry-After": str(seconds)})

    async def failure(self, request: web.Request, name: str | None, what: str,
                      keys: tuple[tuple[str, str], ...] = ()) -> ApiProblem:
        """Audit a failed authentication and make its 401 (counted in `throttled` while its
        peer backs off)."""
        peer = ("peer", request.remote or "?")
        if self.backoff.wait_s(peer) > 0:
            self.throttled += 1
        await self.refused(request, Principal(name, None, "failed"), "login", "failed", 401,
                           {"route": route(request), "reason": what})
        self.backoff.failed(*(keys or (peer,)))
        return ApiProblem(401, f"authentication failed: {what}", headers=CHALLENGE)

    # -- sessions (the page's login) ----------------------------------------------------------

    def open_session(self, who: Identity) -> str:
        session = new_session()
        self._sessions.keep(session, who)
        return session

    def close_session(self, session: str | None) -> str | None:
        found = self._sessions.forget(session) if session else None
        return found.user if found else None

    def _session(self, session: str | None) -> Principal | None:
        """A live session's user with their role now: a session whose user was removed or
        whose password (or, for the owner, key) changed is over, at its next request."""
        found = self._sessions.find(session) if session else None
        return self.principal(found, "session") if found is not None else None

    # -- the audit trail ----------------------------------------------------------------------

    async def record(self, request: web.Request, who: Principal, action: str, outcome: str,
                     status: int, detail: dict[str, Any] | None = None) -> None:
        """What a request did (or a login, a logout): written before it is answered."""
        await self._append(_entry(request, who, action, outcome, status, detail))

    async def refused(self, request: web.Request, who: Principal, action: str, outcome: str,
                      status: int, detail: dict[str, Any] | None = None) -> None:
        """A request refused at the gate (401, 403, 429): the first of its kind written before
        it is answered, its repeats counted into one record per window (refusals.py), so that
        a flood costs neither an fsync a request nor the trail's older records."""
        await self.refusals.refused(_entry(request, who, action, outcome, status, detail),
                                    route(request))

    async def _append(self, entry: dict[str, Any]) -> None:
        try:
            written = await asyncio.to_thread(self.audit.append, entry)
        except OSError as exc:  # the action stands; the failure to record it is loud
            log.error("audit trail %s not written: %s", self.audit.path, exc)
            return
        self.anchor = (written["seq"], written["hash"])


def route(request: web.Request) -> str:
    return f"{request.method} {request.path[:100]}"


def _entry(request: web.Request, who: Principal, action: str, outcome: str, status: int,
           detail: dict[str, Any] | None) -> dict[str, Any]:
    return {**who.audit(), "peer": request.remote, "iface": "http", "action": action,
            "outcome": outcome, "status": status, "detail": detail or {}}


def _basic(value: str) -> tuple[str, str] | None:
    """user:password from a Basic header's value; None when it is not that."""
    try:
        text = base64.b64decode(value.strip(), validate=True).decode("utf-8")
    except (binascii.Error, UnicodeDecodeError):
        return None
    name, colon, password = text.partition(":")
    return (name, password) if colon else None
