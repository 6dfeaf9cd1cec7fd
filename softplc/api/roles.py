"""Which act each HTTP route asks for (docs/security.md, docs/api.md): the HTTP door's map
onto security/roles.py's one table.

Owns: ROUTE_ACTS ((method, route pattern) -> the act, or None for a public route),
ROUTE_ROLES (the same routes -> the least role, derived from COMMAND_ROLES), `route_act` and
`required_role`. A route missing from the table is ADMINISTER, which needs admin: a new route
is closed until it is listed here (tests/security/test_doors.py checks every served route).
Does not know: aiohttp, users, credentials, how a request proves who sent it.
"""

from __future__ import annotations

from typing import Final

from softplc.api.openapi import API_PREFIX
from softplc.security.roles import Act, Role, needs

__all__ = ["ROUTE_ACTS", "ROUTE_ROLES", "Role", "changes_state", "required_role", "route_act"]

_P: Final = API_PREFIX
# (method, aiohttp's canonical route pattern) -> the act; None: served to anybody (the page
# and its files carry no data; login checks its own credentials). HEAD is GET.
ROUTE_ACTS: Final[dict[tuple[str, str], Act | None]] = {
    ("GET", "/healthz"): None,
    ("GET", "/"): None,
    ("GET", "/index.html"): None,
    ("GET", "/static"): None,
    ("POST", f"{_P}/login"): None,
    ("POST", f"{_P}/logout"): None,
    ("GET", f"{_P}/status"): Act.READ,
    ("GET", f"{_P}/whoami"): Act.READ,
    ("GET", f"{_P}/commands/{{id}}"): Act.READ,
    ("GET", f"{_P}/events"): Act.READ,
    ("GET", f"{_P}/openapi.json"): Act.READ,
    ("GET", f"{_P}/program"): Act.READ,
    ("GET", f"{_P}/symbols"): Act.READ,
    ("GET", f"{_P}/symbols/{{name}}"): Act.READ,
    ("GET", f"{_P}/net"): Act.READ,
    ("GET", f"{_P}/live"): Act.READ,
    ("GET", f"{_P}/forces"): Act.READ,
    ("GET", f"{_P}/why/{{transition}}"): Act.READ,  # docs/debug.md
    ("GET", f"{_P}/breakpoints"): Act.READ,
    ("GET", f"{_P}/history"): Act.READ,  # docs/debug.md, the recent past
    ("POST", f"{_P}/start"): Act.START,
    ("POST", f"{_P}/stop"): Act.STOP,
    ("POST", f"{_P}/resume"): Act.RESUME,
    ("PUT", f"{_P}/symbols/{{name}}"): Act.WRITE,
    ("POST", f"{_P}/program"): Act.DOWNLOAD,
    ("POST", f"{_P}/reset"): Act.RESET,
    ("POST", f"{_P}/kill"): Act.KILL,
    ("PUT", f"{_P}/forces/{{name}}"): Act.FORCE,
    ("DELETE", f"{_P}/forces/{{name}}"): Act.UNFORCE,
    ("DELETE", f"{_P}/forces"): Act.UNFORCE,
    ("POST", f"{_P}/breakpoints"): Act.BREAK,
    ("DELETE", f"{_P}/breakpoints"): Act.UNBREAK,
    ("DELETE", f"{_P}/breakpoints/{{id}}"): Act.UNBREAK,
    ("POST", f"{_P}/step"): Act.STEP,
    ("POST", f"{_P}/continue"): Act.CONTINUE,
    ("GET", f"{_P}/audit"): Act.AUDIT,
    ("GET", f"{_P}/audit/events"): Act.AUDIT,  # the trail as it grows (auditstream.py)
}
ROUTE_ROLES: Final[dict[tuple[str, str], Role | None]] = {
    route: None if act is None else needs(act) for route, act in ROUTE_ACTS.items()}


def route_act(method: str, route: str | None) -> Act | None:
    """The act of a request. `route` is the matched route's pattern; None when no route
    matched (the answer is 404 or 405, which a viewer may read). None: a public route."""
    if route is None:
        return Act.READ
    verb = "GET" if method == "HEAD" else method
    return ROUTE_ACTS.get((verb, route), Act.ADMINISTER)


def required_role(method: str, route: str | None) -> Role | None:
    """The least role for a request (None: a public route)."""
    act = route_act(method, route)
    return None if act is None else needs(act)


def changes_state(method: str) -> bool:
    """Whether a request may change something (and is written to the audit trail)."""
    return method not in ("GET", "HEAD", "OPTIONS")
