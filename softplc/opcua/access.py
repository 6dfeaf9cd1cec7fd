"""Who may do what on the OPC UA server (issue 31), and the audit records of what they did.

Owns: the sessions' users: a user-name token is proven by security/decide.py's Authority
(scrypt, in a thread before ActivateSession reaches asyncua, whose user manager is
synchronous), the owner's key as password is the owner (admin; any user name: the old single
token), no identity is anonymous: a viewer, and only on a loopback bind; the back-off of
failed logins per user name and per peer; which act each method is (METHOD_ACTS: the role is
security/roles.py's, as at every door), each request decided by the Authority as the users
file is now (a removed or demoted user's session loses its rights at its next request); the
service ruleset; appending
records to the audit trail (interface "opcua", in a thread: it fsyncs).
Does not know: symbols, the channel, the address space.
"""

from __future__ import annotations

import asyncio
import dataclasses
import enum
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from asyncua import ua
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.server.internal_session import InternalSession
from asyncua.server.user_managers import UserManager

from softplc.opcua.ids import numeric_id
from softplc.security.audit import AuditTrail
from softplc.security.backoff import Backoff
from softplc.security.decide import Authority, Decision, Identity, anonymous
from softplc.security.remembered import PAIRS_KEPT, PAIRS_S, Remembered, pair
from softplc.security.roles import Act, Role
from softplc.security.users import UserStore

log = logging.getLogger(__name__)

# Part 10's methods and Download -> the act of the same command at every door (Halt = kill);
# the role each needs is security/roles.py's COMMAND_ROLES, as for HTTP.
METHOD_ACTS: Final = {"Start": Act.START, "Suspend": Act.STOP, "Resume": Act.RESUME,
                      "Halt": Act.KILL, "Reset": Act.RESET, "Download": Act.DOWNLOAD}


@dataclass
class PlcUser(User):
    """asyncua's session user with softplc's identity; its role is decided at every request
    (security/decide.py): a removed or demoted user's open session loses its rights at once."""

    identity: Identity = dataclasses.field(default_factory=lambda: anonymous(None))
    authority: Authority | None = None
    peer: str = "?"

    def decide(self, act: Act) -> Decision:
        if self.authority is None:
            return Decision(self.identity, act, Role.ADMIN, None, "no authority")
        return self.authority.decide(self.identity, act)

    def audit(self) -> dict[str, Any]:
        role = self.decide(Act.READ).role
        return {"user": self.name, "role": role.label if role else None,
                "via": self.identity.via, "peer": self.peer}


class Login(enum.Enum):
    OK = "ok"
    FAILED = "failed"  # a wrong user name or password: audited
    THROTTLED = "throttled"  # backing off: refused unchecked, counted, not audited


def decide(session: InternalSession, act: Act) -> Decision:
    """The one decision point (security/decide.py) for a request of this session."""
    user = session.user
    if isinstance(user, PlcUser):
        return user.decide(act)
    return Decision(anonymous(None), act, Role.ADMIN, None, "not a softplc session")


class Users(UserManager):
    """asyncua's UserManager over STATE_DIR/users. `login` (async) checks a password first;
    `get_user` (asyncua, synchronous) then only looks the verified pair up."""

    def __init__(self, state_dir: Path, owner_token: str, anonymous: bool) -> None:
        self.store = UserStore(state_dir)
        self.authority = Authority(self.store, lambda: self._owner)
        self.backoff = Backoff(state_dir=state_dir)
        self.throttled = 0
        self._owner = owner_token
        self._anonymous = anonymous
        self._verified = Remembered(self.authority, PAIRS_KEPT, PAIRS_S)
        self._kdf: asyncio.Semaphore | None = None

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if not username and password is None:  # anonymous (a certificate alone is no user)
            return self._user(UserRole.Anonymous, None,
                              anonymous(Role.VIEWER)) if self._anonymous else None
        if password is None or username is None:
            return None
        if (owner := self.authority.owner(password)) is not None:
            return self._user(UserRole.User, owner.user, owner)
        who = self._known(username, password)
        return None if who is None else self._user(UserRole.User, username, who)

    def _user(self, role: UserRole, name: str | None, who: Identity) -> PlcUser:
        return PlcUser(role, name, identity=who, authority=self.authority)

    def _known(self, name: str, password: str) -> Identity | None:
        """The identity of a pair `login` verified lately, while it still holds a role (a
        changed password, a removed user end it)."""
        return self._verified.find(pair(name, password))

    async def login(self, name: str, password: str, peer: str) -> Login:
        """Check `name`/`password` before asyncua activates the session with them."""
        if self.authority.owner(password) is not None or \
                self._known(name, password) is not None:
            return Login.OK
        keys = (("user", name[:64]), ("peer", peer))
        if self.backoff.wait_s(*keys) > 0:
            self.throttled += 1
            return Login.THROTTLED
        if self._kdf is None:
            self._kdf = asyncio.Semaphore(1)  # one scrypt at a time: 32 MiB, ~0.3 s each
        async with self._kdf:
            who = await asyncio.to_thread(self.authority.by_password, name, password) \
                if self.authority.known() else None
        if who is None:
            self.backoff.failed(*keys)
            return Login.FAILED
        self.backoff.succeeded(*keys)
        self._verified.keep(pair(name, password), who)
        return Login.OK


class Recorder:
    """Audit records of the OPC UA interface (the trail of security/audit.py, one chain with HTTP
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
