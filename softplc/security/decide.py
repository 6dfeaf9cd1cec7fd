"""The one decision point of "may this identity do this act now", for every door (issue 38).

Owns: Identity (who proved what, and with which credential as the store held it then),
Decision (allowed or why not, in one line), and Authority: proving identities (the owner's
key, an API key, a user's password) and deciding an act against the users file as it is
*now*. A door may keep an identity for as long as it likes (an HTTP session, a cached Basic
pair, an OPC UA session, an event stream): every decision looks the user up again, so a
changed password or key, a removed user and a changed role act at the next request, at
every door.
Does not know: HTTP, OPC UA, Modbus, back-off, the audit trail.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Final

from softplc.security.roles import Act, Role, needs
from softplc.security.users import OWNER, User, UserError, UserStore

log = logging.getLogger(__name__)

# How an identity was proven. Proven ones (the owner's key, an API key, a password) name a
# user of the users file (or the owner) and are checked against it at every decision; GRANTED
# ones carry the role their door's own rule gives (no credentials on loopback, a client
# certificate's role, a Modbus write policy).
OWNER_VIA: Final = "owner"
GRANTED: Final = frozenset({"anonymous", "certificate", "policy"})


@dataclass(frozen=True, slots=True)
class Identity:
    """Who a request is from. `proof` is the credential as the store held it when proven
    (the password hash, the key's digest, the owner's key's digest); `granted` the role of a
    GRANTED identity (None: may do nothing)."""

    user: str | None
    via: str
    proof: str = ""
    granted: Role | None = None


@dataclass(frozen=True, slots=True)
class Decision:
    who: Identity
    act: Act
    need: Role
    role: Role | None  # what the identity holds now; None: nothing (removed, changed, none)
    why_none: str = ""  # why it holds nothing, when it held something once

    @property
    def allowed(self) -> bool:
        return self.role is not None and self.role >= self.need

    def reason(self) -> str:
        """Why a refused act was refused, in one line."""
        held = self.role.label if self.role is not None else "no role"
        whom = self.who.user or "a client without credentials"
        text = f"{self.act.value} needs {self.need.label}; {whom} has {held}"
        return f"{text} ({self.why_none})" if self.why_none else text


def anonymous(role: Role | None) -> Identity:
    return Identity(None, "anonymous", granted=role)


def granted(who: Identity, act: Act) -> Decision:
    """The decision for an identity whose door grants its role, with no users file to ask
    (a Modbus/TCP Security certificate's role, a Modbus write policy, no credentials);
    Authority.decide holds them to the same rule. A proven identity holds nothing here."""
    if who.via not in GRANTED:
        return Decision(who, act, needs(act), None, "no users file at this door")
    return Decision(who, act, needs(act), who.granted)


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


class Authority:
    """Proves identities and decides acts for one service, over STATE_DIR/users and the
    owner's key (`owner`: the key as it is now: a rotated key ends the old one's rights)."""

    def __init__(self, users: UserStore, owner: Callable[[], str]) -> None:
        self.users = users
        self._owner = owner
        self._problem = ""  # the users file's problem as last logged ("" when usable)

    # -- proving --------------------------------------------------------------------------------

    def owner(self, secret: str) -> Identity | None:
        """The owner, if `secret` is the owner's key (constant time)."""
        token = self._owner()
        if secret and token and hmac.compare_digest(secret.encode(), token.encode()):
            return Identity(OWNER, OWNER_VIA, _digest(token))
        return None

    def by_key(self, key: str) -> Identity | None:
        user = self.users.verify_key(key) if self.known() else None
        return None if user is None or user.key_sha256 is None else \
            Identity(user.name, "key", user.key_sha256)

    def by_password(self, name: str, password: str) -> Identity | None:
        """The identity of `name` if `password` is theirs. Blocking (scrypt): in a thread."""
        user = self.known().get(name)
        try:
            verified = self.users.verify(name, password)
        except UserError:  # unusable (logged by known()): nobody but the owner gets in
            return None
        if verified is None or user is None:
            return None
        # the hash verified, as read before it: a change in between is caught at the decision
        return Identity(user.name, "password", user.password)

    def known(self) -> dict[str, User]:
        """The users as the file holds them now ({} when it is unusable: owner only). An
        unusable file is logged once per change of its problem (every request asks), and its
        repair once."""
        try:
            users = self.users.users()  # read again when the file changed
        except UserError as exc:
            if str(exc) != self._problem:
                self._problem = str(exc)
                log.error("%s", exc)
            return {}
        if self._problem:
            self._problem = ""
            log.info("%s is usable again", self.users.path)
        return users

    # -- deciding -------------------------------------------------------------------------------

    def role_now(self, who: Identity) -> tuple[Role | None, str]:
        """The role `who` holds now, and why it holds none when it was proven once."""
        if who.via in GRANTED:
            return who.granted, ""
        if who.via == OWNER_VIA:
            token = self._owner()
            return (Role.ADMIN, "") if token and who.proof == _digest(token) else \
                (None, "the owner's key was replaced")
        user = self.known().get(who.user or "")
        if user is None:
            return None, "the user was removed"
        if who.via == "key":
            return (user.role, "") if user.key_sha256 == who.proof else \
                (None, "the API key was replaced or revoked")
        if who.via == "password":
            return (user.role, "") if user.password == who.proof else \
                (None, "the password was changed")
        return None, f"unknown proof {who.via!r}"

    def decide(self, who: Identity, act: Act) -> Decision:
        role, why = self.role_now(who)
        return Decision(who, act, needs(act), role, why)
