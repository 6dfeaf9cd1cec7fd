"""Roles and the one table of which role each HTTP route needs (docs/security.md, docs/api.md).

Owns: Role (viewer < operator < engineer < admin, each holding the rights of those below),
ROUTE_ROLES ((method, route pattern) -> the least role, or None for a public route), and
`required_role`. A route missing from the table needs ADMIN: a new route is closed until
it is listed here (tests/security/test_roles.py checks that every served route is).
Does not know: aiohttp, users, credentials, how a request proves who sent it.
"""

from __future__ import annotations

import enum
from typing import Final

from softplc.api.openapi import API_PREFIX


class Role(enum.IntEnum):
    """What a user may do; a higher role may do everything a lower one may."""

    VIEWER = 1  # read: status, symbols, events, the program, the page
    OPERATOR = 2  # start, stop, resume, symbol (HMI) writes
    ENGINEER = 3  # download, reset, kill, force and unforce
    ADMIN = 4  # users, keys, the audit trail

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, text: str) -> Role:
        """A role from its name (`operator`); ValueError naming the choices otherwise."""
        try:
            return cls[text.strip().upper()]
        except KeyError:
            raise ValueError(f"unknown role {text!r}: one of "
                             f"{', '.join(r.label for r in cls)}") from None


_P: Final = API_PREFIX
# (method, aiohttp's canonical route pattern) -> the least role; None: served to anybody
# (the page and its files carry no data; login checks its own credentials). HEAD is GET.
ROUTE_ROLES: Final[dict[tuple[str, str], Role | None]] = {
    ("GET", "/healthz"): None,
    ("GET", "/"): None,
    ("GET", "/index.html"): None,
    ("GET", "/static"): None,
    ("POST", f"{_P}/login"): None,
    ("POST", f"{_P}/logout"): None,
    ("GET", f"{_P}/status"): Role.VIEWER,
    ("GET", f"{_P}/whoami"): Role.VIEWER,
    ("GET", f"{_P}/commands/{{id}}"): Role.VIEWER,
    ("GET", f"{_P}/events"): Role.VIEWER,
    ("GET", f"{_P}/openapi.json"): Role.VIEWER,
    ("GET", f"{_P}/program"): Role.VIEWER,
    ("GET", f"{_P}/symbols"): Role.VIEWER,
    ("GET", f"{_P}/symbols/{{name}}"): Role.VIEWER,
    ("GET", f"{_P}/net"): Role.VIEWER,
    ("GET", f"{_P}/live"): Role.VIEWER,
    ("GET", f"{_P}/forces"): Role.VIEWER,
    ("GET", f"{_P}/why/{{transition}}"): Role.VIEWER,  # docs/debug.md
    ("GET", f"{_P}/breakpoints"): Role.VIEWER,
    ("GET", f"{_P}/history"): Role.VIEWER,  # docs/debug.md, the recent past
    ("POST", f"{_P}/start"): Role.OPERATOR,
    ("POST", f"{_P}/stop"): Role.OPERATOR,
    ("POST", f"{_P}/resume"): Role.OPERATOR,
    ("PUT", f"{_P}/symbols/{{name}}"): Role.OPERATOR,
    ("POST", f"{_P}/program"): Role.ENGINEER,
    ("POST", f"{_P}/reset"): Role.ENGINEER,
    ("POST", f"{_P}/kill"): Role.ENGINEER,
    ("PUT", f"{_P}/forces/{{name}}"): Role.ENGINEER,
    ("DELETE", f"{_P}/forces/{{name}}"): Role.ENGINEER,
    ("DELETE", f"{_P}/forces"): Role.ENGINEER,
    # Breakpoints and single scans (docs/debug.md): they stop a machine's program mid-way.
    ("POST", f"{_P}/breakpoints"): Role.ENGINEER,
    ("DELETE", f"{_P}/breakpoints"): Role.ENGINEER,
    ("DELETE", f"{_P}/breakpoints/{{id}}"): Role.ENGINEER,
    ("POST", f"{_P}/step"): Role.ENGINEER,
    ("POST", f"{_P}/continue"): Role.ENGINEER,
    ("GET", f"{_P}/audit"): Role.ADMIN,
    ("GET", f"{_P}/audit/events"): Role.ADMIN,  # the trail as it grows (auditstream.py)
}
UNLISTED: Final = Role.ADMIN


def required_role(method: str, route: str | None) -> Role | None:
    """The least role for a request. `route` is the matched route's pattern; None when no
    route matched (the answer is 404 or 405, which a viewer may read)."""
    if route is None:
        return Role.VIEWER
    verb = "GET" if method == "HEAD" else method
    return ROUTE_ROLES.get((verb, route), UNLISTED)


def changes_state(method: str) -> bool:
    """Whether a request may change something (and is written to the audit trail)."""
    return method not in ("GET", "HEAD", "OPTIONS")
