"""The debugging routes (issue 32): `GET /api/v1/why/{transition}`, read-only (viewer), and
breakpoints and single scans (engineer; `GET /api/v1/breakpoints` viewer): `POST|DELETE
/api/v1/breakpoints`, `DELETE /api/v1/breakpoints/{id}`, `POST /api/v1/step`, `/continue`,
sent as commands to the scan (core/pausing.py applies them at a scan boundary).

Owns: explaining a transition of the running program in this (the communication) process,
off the scan: the net compiled here once per program hash from the boot program the PLC keeps
in its state directory (program/boot.py), and the round's state rebuilt from one status board
document (marking, coloured tokens, symbol values, forces, delays and timed firings in
progress), so that marking and values belong to the same scan, typed and scaled as the scan
reads them. core/why.py does the rest.
Does not know: the scan process (nothing is asked of it), the channel.

What the board does not carry is said in the answer's `basis`: the previous scan's values
(an edge, `rising(x)`, reads as no edge) and the events of the coming round (none); a coloured
place shows its first 20 tokens.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import tempfile
from pathlib import Path
from typing import Any, Final

from aiohttp import web

from softplc.api.openapi import API_PREFIX
from softplc.api.problems import ApiProblem, json_body
from softplc.api.service import ApiService
from softplc.core.breakpoints import On, Outputs, spec
from softplc.core.context import ScanContext
from softplc.core.datatypes import SymType
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.net import Busy, CompiledNet, NetState
from softplc.core.present import ValueRefused, accepted
from softplc.core.problems import ProgramError
from softplc.core.snapshot import CommandReply
from softplc.core.symbols import scalings
from softplc.core.why import Why, explain
from softplc.program import boot
from softplc.program import bundle as bundles
from softplc.program.compiler import compile_file, compile_text

_BREAK_ID: Final = re.compile(r"break: (b\d+): ")
BASIS: Final = ("the next firing round, on the marking and symbol values of the status board "
                "of scan {scan} (refreshed about every 50 ms); events and edges of that round "
                "are not published and read as none")


def register(app: web.Application, api: ApiService) -> None:
    """Add the debugging routes to `app` (server.py's build_app calls this once)."""
    routes = _Routes(api)
    app.router.add_get(f"{API_PREFIX}/why/{{transition}}", routes.why)
    app.router.add_get(f"{API_PREFIX}/breakpoints", routes.breakpoints)
    app.router.add_post(f"{API_PREFIX}/breakpoints", routes.add_break)
    app.router.add_delete(f"{API_PREFIX}/breakpoints", routes.remove_break)
    app.router.add_delete(f"{API_PREFIX}/breakpoints/{{id}}", routes.remove_break)
    app.router.add_post(f"{API_PREFIX}/step", routes.step)
    app.router.add_post(f"{API_PREFIX}/continue", routes.resume)


def compile_boot(state_dir: Path) -> CompiledNet | None:
    """The boot program of `state_dir` compiled (a bundle unpacked into a temporary folder),
    None when there is none. Raises ProgramError, BundleError, BootUnreadable, OSError."""
    program = boot.load(state_dir)
    if program is None:
        return None
    if program.bundle is None:
        return compile_text(program.text, program.filename,
                            Path(program.root) if program.root else None)
    bundle = bundles.unpack(program.bundle)
    with tempfile.TemporaryDirectory(prefix="softplc-why-") as folder:
        root = (Path(folder) / "bundle").resolve()
        return compile_file(bundles.extract(bundle, root), root)


def state_of(net: CompiledNet, doc: dict[str, Any]) -> tuple[NetState, ScanContext, int]:
    """The round's NetState, context and `now_ns` rebuilt from a board document."""
    state = NetState.initial(net)
    state.marking[:] = 0
    for place, count in (doc.get("marking") or {}).items():
        if place in net.place_index:
            state.marking[net.place_index[place]] = int(count)
    state.tokens = {p: [] for p in state.tokens}
    for place, records in (doc.get("tokens") or {}).items():
        if place in net.place_index:
            state.tokens[net.place_index[place]] = [dict(r) for r in records]
    live = doc.get("net_live") or {}
    now_ns = 0  # the board's times are remaining times: they count from here
    index = {t.name: t for t in net.transitions}
    for name, left_ms in (live.get("delay_left_ms") or {}).items():
        if name in index:
            state.enabled_since[index[name].index] = \
                int(float(left_ms) * 1e6) - index[name].delay_ns
    busy = live.get("busy")
    for name, times in (busy if isinstance(busy, dict) else {}).items():
        if name in index:
            t = index[name]
            produce = tuple((o.place, o.weight, None) for o in t.post)
            state.busy[t.index] = Busy(int(float(times.get("remaining_ms", 0)) * 1e6), produce)
    image = ProcessImage(net.io.sizes)
    for name, entry in (doc.get("symbols") or {}).items():
        symbol = net.io.symbols.get(name)
        if symbol is not None and isinstance(entry, dict):
            with contextlib.suppress(TypeError, ValueError, OverflowError):
                image.set(symbol.address, entry["raw"] if "raw" in entry  # the bits
                          else accepted(symbol.type.value, entry.get("value", 0), name,
                                        symbol.scaling))
    symbols = net.io.symbols.values()
    locations = {s.name: (s.address.attr, s.address.index) for s in symbols}
    # As the scan's context (core/plc.py): a real's bits read as a real, a scaled int in
    # engineering units, so that the guard and the values shown are the program's.
    typed = {s.name: s.type for s in symbols if s.type not in (SymType.BOOL, SymType.WORD)}
    ctx = ScanContext(image, image, locations, frozenset(), typed, scalings(net.io))
    return state, ctx, now_ns


def forced_of(net: CompiledNet, doc: dict[str, Any]) -> dict[str, object]:
    """The board's forces (shown as people read them) as the raw bits the scan keeps; a value
    that does not convert back (a NaN real, shown as text) stays as shown."""
    out: dict[str, object] = {}
    for name, shown_value in (doc.get("forced") or {}).items():
        sym = net.io.symbols.get(name)
        try:
            out[name] = shown_value if sym is None else accepted(
                sym.type.value, shown_value, name, sym.scaling)
        except ValueRefused:
            out[name] = shown_value
    return out


def explain_board(net: CompiledNet, doc: dict[str, Any], name: str) -> Why:
    """Why transition `name` fires or not in the next round after the board `doc`'s scan."""
    state, ctx, now_ns = state_of(net, doc)
    return explain(net, state, ctx, now_ns, name, forced_of(net, doc))


class _Routes:
    def __init__(self, api: ApiService) -> None:
        self._api = api
        self._net: CompiledNet | None = None
        self._lock = asyncio.Lock()

    async def _program(self, program_hash: str) -> CompiledNet:
        """The running program, compiled here once per hash (a new download: again)."""
        async with self._lock:
            if self._net is not None and self._net.program_hash == program_hash:
                return self._net
            try:
                net = await asyncio.to_thread(compile_boot, self._api.state_dir)
            except (ProgramError, bundles.BundleError, boot.BootUnreadable, OSError) as exc:
                raise ApiProblem(409, f"the running program cannot be read back from the "
                                      f"state directory: {exc}") from None
            if net is None or net.program_hash != program_hash:
                raise ApiProblem(409, "the running program is not the kept boot program yet "
                                      "(a download is being stored); try again",
                                 headers={"Retry-After": "1"})
            self._net = net
            return net

    async def why(self, request: web.Request) -> web.Response:
        name = request.match_info["transition"]
        doc = await self._api.board_document()
        program_hash = doc.get("program_hash")
        if not program_hash:
            raise ApiProblem(404, f"no program is loaded: no transition {name!r}")
        net = await self._program(str(program_hash))
        if name not in {t.name for t in net.transitions}:
            raise ApiProblem(404, f"no transition {name!r} in program {net.name}",
                             [f"transitions: {', '.join(t.name for t in net.transitions[:50])}"])
        answer = await asyncio.to_thread(explain_board, net, doc, name)
        scan = doc.get("scan_count", 0)
        body = {**answer.as_dict(), "program": net.name, "state": doc.get("state"),
                "scan": scan, "basis": BASIS.format(scan=scan)}
        if doc.get("state") != "RUNNING":
            body["note"] = f"the PLC is {doc.get('state')}: no round runs until it runs"
        return web.json_response(body)

    # -- breakpoints and single scans (docs/debug.md) -------------------------------------------

    async def breakpoints(self, request: web.Request) -> web.Response:
        doc = await self._api.board_document()
        return web.json_response({"breakpoints": doc.get("breakpoints") or [],
                                  "paused": doc.get("paused"),
                                  "steps_left": doc.get("steps_left", 0),
                                  "scan_count": doc.get("scan_count", 0)})

    async def add_break(self, request: web.Request) -> web.Response:
        body = await json_body(request)
        if not isinstance(body, dict):
            raise ApiProblem(400, 'the body must be a JSON object like {"on": "fire", '
                                  '"transition": "t1"} or {"on": "when", "condition": "..."}')
        try:
            on, outputs = On(body.get("on", "fire")), Outputs(body.get("outputs", "hold"))
        except ValueError:
            raise ApiProblem(422, "break refused: `on` is fire, enabled or when; `outputs` "
                                  "is hold or safe") from None
        target = body.get("condition" if on is On.WHEN else "transition")
        if not isinstance(target, str) or not target.strip():
            raise ApiProblem(422, f"break refused: `on: {on.value}` needs "
                                  + ("a `condition`" if on is On.WHEN else "a `transition`"))
        reply = await self._api.command(
            Command.BREAK, symbol=spec(on, target), value=int(outputs is Outputs.SAFE))
        # The breakpoint's id (b1, b2, ...) as the scan named it ("break: b3: t fires ..."),
        # beside the command's: what a client removes it by.
        named = _BREAK_ID.match(reply.message) if isinstance(reply, CommandReply) else None
        return self._reply(reply, {"breakpoint": named.group(1)} if named else {})

    async def remove_break(self, request: web.Request) -> web.Response:
        ident = request.match_info.get("id")
        if ident is not None and not ident.removeprefix("b").isdigit():
            raise ApiProblem(404, f"no breakpoint {ident[:40]!r}: ids are b1, b2, ... or 1, 2")
        return self._reply(await self._api.command(Command.UNBREAK, symbol=ident))

    async def step(self, request: web.Request) -> web.Response:
        text = request.query.get("scans", "1")
        if not text.isdigit() or not 1 <= int(text) <= 1_000_000:
            raise ApiProblem(400, f"scans must be a whole number 1..1000000, not {text[:40]!r}")
        return self._reply(await self._api.command(Command.STEP, value=int(text)))

    async def resume(self, request: web.Request) -> web.Response:
        return self._reply(await self._api.command(Command.CONTINUE))

    def _reply(self, reply: Any, extra: dict[str, Any] | None = None) -> web.Response:
        """A refused breakpoint (a transition or name the program lacks) is 422, a command
        the state refuses (step while not paused) 409."""
        if not isinstance(reply, CommandReply):  # pending: the command contract's 202
            return self._api.answer(reply)
        if not reply.ok:
            status = 422 if " refused: " in reply.message else 409
            raise ApiProblem(status, reply.message, state=reply.state.name)
        return web.json_response({"ok": True, "message": reply.message,
                                  "state": reply.state.name, "id": reply.id, **(extra or {})})
