"""The access check around every HTTP route, and the routes of access itself.

Owns: `admit` (the role a route needs, from roles.py, against the request's principal:
401 without credentials, 403 with a role too low, the denial audited when the request would
have changed something), `audited` (a state-changing request's record: who, what, the
program hash or the value written, the outcome), and the routes `POST /api/v1/login`,
`POST /api/v1/logout` (the page's session cookie), `GET /api/v1/whoami`, `GET
/api/v1/audit` and its stream `GET /api/v1/audit/events` (admin; auditstream.py).
Does not know: how credentials are checked (access.py), the trail's files (audit.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
from collections.abc import Awaitable, Callable
from typing import Any, Final

from aiohttp import web

from softplc.api.access import COOKIE, PRINCIPAL, Gate, Principal
from softplc.api.auditstream import AuditStreams
from softplc.api.openapi import API_PREFIX
from softplc.api.problems import ApiProblem, json_body
from softplc.api.roles import changes_state, route_act
from softplc.security.audit import parse_since
from softplc.security.remembered import SESSION_S

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
MAX_LIMIT: Final = 10_000


def route_of(request: web.Request) -> str | None:
    resource = request.match_info.route.resource
    return resource.canonical if resource is not None else None


async def admit(gate: Gate, request: web.Request) -> Principal | None:
    """The principal a request runs as, or None for a public route; raises 401/403/429.
    Decided by the one decision point (security/decide.py) on the route's act."""
    act = route_act(request.method, route_of(request))
    if act is None:
        return None
    who = await gate.identify(request)
    decision = gate.decide(who, act)
    if decision.allowed:
        return who
    what = f"{request.method} {request.path[:100]} needs {decision.need.label}"
    if who.user is None:
        problem = ApiProblem(401, f"{what}: give credentials (an API key as a bearer token, "
                             "user and password, or STATE_DIR/api_token on this machine)"
                             + (f"; without them this service allows {who.role.label}"
                                if who.role else ""), headers={"WWW-Authenticate":
                                                               'Bearer realm="softplc"'})
    else:
        problem = ApiProblem(403, f"{what}; {who.user} is "
                             f"{decision.role.label if decision.role else '?'}"
                             + (f" ({decision.why_none})" if decision.why_none else ""))
    if changes_state(request.method):
        await gate.refused(request, who, action(request), "denied", problem.status,
                           {"needs": decision.need.label})
    raise problem


def action(request: web.Request) -> str:
    return f"{request.method} {request.path.removeprefix(API_PREFIX + '/')[:100]}"


# Requests refused for their form before they reached the PLC (bad JSON, an unknown symbol,
# too large): their repeats are counted into one record per window (docs/security.md,
# "Refused requests"). A command the PLC refused (409) or a rejected program (422) stays one
# record each: an operator's action, with its outcome.
MALFORMED: Final = frozenset((400, 404, 405, 411, 413, 414, 415, 431))


async def audited(gate: Gate, request: web.Request, who: Principal | None,
                  handler: Handler) -> web.StreamResponse:
    """Run a request; when it may change something, write its record (whatever the
    outcome). Login and logout write their own."""
    if who is None or not changes_state(request.method):
        return await handler(request)
    try:
        response = await handler(request)
    except ApiProblem as problem:
        await _write(gate, request, who, problem.status, problem.error)
        raise
    except web.HTTPException as exc:
        await _write(gate, request, who, exc.status, exc.reason)
        raise
    except Exception:
        await _write(gate, request, who, 500, "internal error")
        raise
    message = None
    if isinstance(response, web.Response) and isinstance(response.body, bytes):
        with contextlib.suppress(ValueError, AttributeError):
            message = json.loads(response.body).get("message")
    await _write(gate, request, who, response.status, message)
    return response


async def _write(gate: Gate, request: web.Request, who: Principal, status: int,
                 message: str | None) -> None:
    outcome = ("applied" if status in (200, 201, 204) else "queued" if status == 202
               else "refused" if status < 500 else "failed")
    detail: dict[str, Any] = {"message": message} if message else {}
    # The handler read it (the stream at its end): cached, no wait. (`can_read_body` is
    # false once read: asked alone, no download's hash or flags reached the trail.)
    if status not in (408, 413) and request.body_exists and not request.can_read_body:
        with contextlib.suppress(Exception):
            body = await asyncio.wait_for(request.read(), 1.0)
            detail.update(_what(request, body))
    if status in MALFORMED:  # a flood of them (JSON bombs) coalesced as the gate's refusals
        await gate.refused(request, who, action(request), outcome, status, detail)
    else:
        await gate.record(request, who, action(request), outcome, status, detail)


def _what(request: web.Request, body: bytes) -> dict[str, Any]:
    """The program's hash for a download, the value for a symbol write or a force."""
    if request.path == f"{API_PREFIX}/program":
        return {"body_sha256": hashlib.sha256(body).hexdigest(), "bytes": len(body),
                **{k: v for k, v in request.query.items()
                   if k in ("name", "online", "replace", "dry_run", "allow_older")}}
    with contextlib.suppress(ValueError, AttributeError):
        return {"value": json.loads(body).get("value")}
    return {}


# -- the routes of access -------------------------------------------------------------------

def register(app: web.Application, gate: Gate, heartbeat_s: float) -> None:
    routes = _Routes(gate)
    streams = AuditStreams(gate, heartbeat_s)
    p = API_PREFIX
    app.router.add_post(f"{p}/login", routes.login)
    app.router.add_post(f"{p}/logout", routes.logout)
    app.router.add_get(f"{p}/whoami", routes.whoami)
    app.router.add_get(f"{p}/audit", routes.audit)
    app.router.add_get(f"{p}/audit/events", streams.serve)
    app.on_shutdown.append(streams.close)


class _Routes:
    def __init__(self, gate: Gate) -> None:
        self._gate = gate

    async def login(self, request: web.Request) -> web.Response:
        """User and password as JSON ({"user", "password"}) or HTTP Basic -> a session
        cookie (HttpOnly, SameSite=Strict, Secure over TLS) for the page."""
        if "Authorization" in request.headers:
            who = await self._gate.identify(request)
        else:
            body = await json_body(request)
            if not isinstance(body, dict) or not isinstance(body.get("user"), str) \
                    or not isinstance(body.get("password"), str):
                raise ApiProblem(400, 'login takes {"user": "...", "password": "..."}')
            who = self._gate.principal(await self._gate.password(request, body["user"],
                                                                 body["password"]))
        name, role = who.user, who.role
        if name is None or role is None or who.identity is None:
            raise ApiProblem(401, "authentication failed: no user")
        response = web.json_response({"user": name, "role": role.label})
        response.set_cookie(COOKIE, self._gate.open_session(who.identity),
                            max_age=int(SESSION_S),
                            path="/", httponly=True, samesite="Strict", secure=request.secure)
        await self._gate.record(request, Principal(name, role, "session"), "login", "applied",
                                200)
        return response

    async def logout(self, request: web.Request) -> web.Response:
        name = self._gate.close_session(request.cookies.get(COOKIE))
        response = web.json_response({"ok": True})
        response.del_cookie(COOKIE, path="/")
        if name is not None:
            await self._gate.record(request, Principal(name, None, "session"), "logout",
                                    "applied", 200)
        return response

    async def whoami(self, request: web.Request) -> web.Response:
        who = PRINCIPAL.get() or Principal(None, None, "anonymous")
        return web.json_response({"user": who.user, "role": who.role.label if who.role
                                  else None, "via": who.via})

    async def audit(self, request: web.Request) -> web.Response:
        """The newest records (`limit`, default 1000), at or after `since`, with the
        chain's verdict."""
        try:
            since = parse_since(request.query["since"]) if "since" in request.query else None
            limit = int(request.query.get("limit", "1000"))
        except ValueError as exc:
            raise ApiProblem(400, str(exc)) from None
        if not 1 <= limit <= MAX_LIMIT:
            raise ApiProblem(400, f"limit must be 1 to {MAX_LIMIT}")
        trail = self._gate.audit
        records, verdict = await asyncio.to_thread(
            lambda: (trail.records(since, limit), trail.verify(self._gate.anchor)))
        return web.json_response({"records": records, "chain": verdict.as_dict()})

