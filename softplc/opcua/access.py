"""Who may do what on the OPC UA server (issue 31), and the audit records of what they did.

Owns: the sessions' users: a user-name token is checked against STATE_DIR/users (api/users.py
`verify`, scrypt, in a thread before ActivateSession reaches asyncua, whose user manager is
synchronous), the owner's key as password is the owner (admin; any user name: the old single
token), no identity is anonymous: a viewer, and only on a loopback bind; the back-off of
failed logins per user name and per peer; which role each action needs (api/roles.py's route
table: the rights are those of the same command over HTTP); the service ruleset; appending
records to the audit trail (interface "opcua", in a thread: it fsyncs).
Does not know: symbols, the channel, the address space.
"""

from __future__ import annotations

import asyncio
import enum
import hashlib
import hmac
import logging
import secrets
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.server.internal_session import InternalSession
from asyncua.server.user_managers import UserManager

from softplc.api.audit import AuditTrail
from softplc.api.backoff import Backoff
from softplc.api.openapi import API_PREFIX
from softplc.api.roles import Role, required_role
from softplc.api.users import OWNER, UserError, UserStore
from softplc.opcua.ids import numeric_id

log = logging.getLogger(__name__)


def _route_role(method: str, route: str) -> Role:
    role = required_role(method, f"{API_PREFIX}/{route}")
    assert role is not None, route
    return role


# Part 10's methods and Download -> the role of the same command over HTTP (Halt = kill).
METHOD_ROLES: Final = {method: _route_role("POST", route) for method, route in (
    ("Start", "start"), ("Suspend", "stop"), ("Resume", "resume"), ("Halt", "kill"),
    ("Reset", "reset"), ("Download", "program"))}
WRITE_ROLE: Final = _route_role("PUT", "symbols/{name}")  # an HMI write of a symbol
VERIFIED_KEPT: Final = 64  # verified name:password pairs: a reconnecting client pays scrypt once
VERIFIED_S: Final = 300.0


@dataclass
class PlcUser(User):
    """asyncua's session user with softplc's role; `plc_role` None: may do nothing."""

    plc_role: Role | None = None
    via: str = ""  # owner, password, anonymous
    peer: str = "?"

    def audit(self) -> dict[str, Any]:
        return {"user": self.name, "role": self.plc_role.label if self.plc_role else None,
                "via": self.via, "peer": self.peer}


class Login(enum.Enum):
    OK = "ok"
    FAILED = "failed"  # a wrong user name or password: audited
    THROTTLED = "throttled"  # backing off: refused unchecked, counted, not audited


def role_of(session: InternalSession) -> Role | None:
    user = session.user
    return user.plc_role if isinstance(user, PlcUser) else None


def may(session: InternalSession, needed: Role) -> bool:
    role = role_of(session)
    return role is not None and role >= needed


class Users(UserManager):
    """asyncua's UserManager over STATE_DIR/users. `login` (async) checks a password first;
    `get_user` (asyncua, synchronous) then only looks the verified pair up."""

    def __init__(self, state_dir: Path, owner_token: str, anonymous: bool) -> None:
        self.store = UserStore(state_dir)
        self.backoff = Backoff()
        self.throttled = 0
        self._owner = owner_token
        self._anonymous = anonymous
        self._pepper = secrets.token_bytes(32)
        self._verified: OrderedDict[bytes, tuple[Role, str, float]] = OrderedDict()
        self._kdf: asyncio.Semaphore | None = None

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if not username and password is None:  # anonymous (a certificate alone is no user)
            return PlcUser(UserRole.Anonymous, None, Role.VIEWER, "anonymous") \
                if self._anonymous else None
        if password is None or username is None:
            return None
        if self._is_owner(password):
            return PlcUser(UserRole.User, OWNER, Role.ADMIN, "owner")
        role = self._known(username, password)
        return None if role is None else PlcUser(UserRole.User, username, role, "password")

    def _is_owner(self, password: str) -> bool:
        return hmac.compare_digest(password.encode(), self._owner.encode())

    def _stamp(self, name: str, password: str) -> bytes:
        return hashlib.sha256(self._pepper + f"{name}\0{password}".encode()).digest()

    def _known(self, name: str, password: str) -> Role | None:
        """The role of a pair `login` verified lately, while the user's role and password
        hash are still those it was verified with (a changed password ends it)."""
        entry = self._verified.get(self._stamp(name, password))
        user = self._users().get(name)
        if entry is None or entry[2] < time.monotonic() or user is None \
                or (user.role, user.password) != entry[:2]:
            return None
        return entry[0]

    def _users(self) -> dict[str, Any]:
        try:
            return dict(self.store.users())  # read again when the file changed
        except UserError as exc:  # an unusable users file: nobody but the owner gets in
            log.error("%s", exc)
            return {}

    async def login(self, name: str, password: str, peer: str) -> Login:
        """Check `name`/`password` before asyncua activates the session with them."""
        if self._is_owner(password) or self._known(name, password) is not None:
            return Login.OK
        keys = (("user", name[:64]), ("peer", peer))
        if self.backoff.wait_s(*keys) > 0:
            self.throttled += 1
            return Login.THROTTLED
        if self._kdf is None:
            self._kdf = asyncio.Semaphore(1)  # one scrypt at a time: 32 MiB, ~0.3 s each
        async with self._kdf:
            users = self._users()
            role = await asyncio.to_thread(self.store.verify, name, password) if users \
                else None
        user = users.get(name)
        if role is None or user is None:
            self.backoff.failed(*keys)
            return Login.FAILED
        self.backoff.succeeded(*keys)
        self._verified[self._stamp(name, password)] = (role, user.password,
                                                       time.monotonic() + VERIFIED_S)
        while len(self._verified) > VERIFIED_KEPT:
            self._verified.popitem(last=False)
        return Login.OK


class Recorder:
    """Audit records of the OPC UA interface (the trail of api/audit.py, one chain with HTTP
    and the CLI). A record that cannot be written is logged; the action stands."""

    def __init__(self, state_dir: Path) -> None:
        self.trail = AuditTrail(state_dir)

    async def record(self, who: dict[str, Any], action: str, outcome: str, status: int,
                     detail: dict[str, Any] | None = None) -> None:
        name = ua.StatusCode(ua.UInt32(status)).name
        entry = {"user": None, "role": None, "via": None, "peer": None, **who,
                 "iface": "opcua", "action": action, "outcome": outcome, "status": name,
                 "detail": detail or {}}
        try:
            await asyncio.to_thread(self.trail.append, entry)
        except OSError as exc:
            log.error("audit trail %s not written: %s", self.trail.path, exc)


def who(session: InternalSession) -> dict[str, Any]:
    user = session.user
    return user.audit() if isinstance(user, PlcUser) else {"user": None, "role": None}


class ClientServices(SimpleRoleRuleset):
    """Which services a session may request at all: every client service, anonymous or not
    (a write or call the session's role does not allow is refused per item, with a status
    code, by the session hooks); changing the address space (AddNodes etc.) for nobody."""

    def __init__(self) -> None:
        # SimpleRoleRuleset's own tables are not used: check_validity is the whole rule.
        self._allowed = frozenset(numeric_id(i) for i in USER_TYPES)

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        return user.role is not UserRole.Admin and action_type_id in self._allowed
