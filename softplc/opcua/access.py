"""Who may do what on the OPC UA server.

Owns: the user manager (a user name with the API token as password is an operator who may
read, write and call; no identity is anonymous and may only read, and only on a loopback
bind), the service ruleset (every client service for everyone, changing the address space
for nobody) and the per-session check that writes and method calls use.
Does not know: symbols, the channel, the address space.
"""

from __future__ import annotations

import hmac
from typing import Any, Final

from asyncua import ua
from asyncua.crypto.permission_rules import (
    USER_TYPES,
    SimpleRoleRuleset,
    User,
    UserRole,
)
from asyncua.server.internal_session import InternalSession
from asyncua.server.user_managers import UserManager

from softplc.opcua.ids import numeric_id

OPERATOR: Final = "operator"  # the documented user name; any name works, the password counts


class TokenUsers(UserManager):
    """asyncua UserManager: a user name with the API token as password is an operator
    (read, write, call); no identity is anonymous (read only), and only on a loopback bind."""

    def __init__(self, token: str, anonymous: bool) -> None:
        self._token = token
        self._anonymous = anonymous

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if not username and password is None:  # anonymous (a certificate alone is no user)
            return User(role=UserRole.Anonymous) if self._anonymous else None
        if password is not None and hmac.compare_digest(str(password).encode(),
                                                        self._token.encode()):
            return User(role=UserRole.User, name=username or OPERATOR)
        return None  # wrong token: BadUserAccessDenied at ActivateSession


class ClientServices(SimpleRoleRuleset):
    """Which services a session may request at all: every client service, anonymous or not
    (a write or call of an anonymous session is refused per item, with a status code, by
    the session hooks); changing the address space (AddNodes etc.) for nobody."""

    def __init__(self) -> None:
        # SimpleRoleRuleset's own tables are not used: check_validity is the whole rule.
        self._allowed = frozenset(numeric_id(i) for i in USER_TYPES)

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        return user.role is not UserRole.Admin and action_type_id in self._allowed


def may_act(session: InternalSession) -> bool:
    """Whether the session's user may write symbols and call methods (not anonymous)."""
    user = session.user
    return user is not None and user.role in (UserRole.User, UserRole.Admin)
