"""The program routes: download (`POST /api/v1/program`, YAML text or a bundle) and upload
(`GET /api/v1/program`, the running program's bundle byte for byte).

Owns: what is checked before a download reaches the scan process (the signature and its
version when keys are trusted: signed.py, `allow_older`; UTF-8, not empty, no character YAML
forbids, a usable bundle, a plain name), telling the gate which signed downloads the PLC took,
and turning a refused download into 422 with one located problem per line.
Does not know: compiling (the scan process does, behind the channel), the lifecycle.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import re
from pathlib import Path
from typing import Final

from aiohttp import web

from softplc.api.commands import Outcome, Record
from softplc.api.openapi import API_PREFIX
from softplc.api.problems import ApiProblem, flag, idempotency_key
from softplc.api.service import ApiService
from softplc.api.signed import SIGNATURE_HEADER, DownloadSigning
from softplc.core.lifecycle import Command
from softplc.core.snapshot import DOWNLOAD_REFUSED, CommandReply
from softplc.program import boot
from softplc.program import bundle as bundles

_NAME: Final = re.compile(r"[A-Za-z0-9._-]{1,128}")
# Characters a YAML stream may not hold (YAML 1.1 section 5.1, as PyYAML's reader checks).
_NOT_YAML: Final = re.compile(
    "[^\x09\x0A\x0D\x20-\x7E\x85\xA0-\uD7FF\uE000-\uFFFD\U00010000-\U0010FFFF]")


def register(app: web.Application, api: ApiService, signing: DownloadSigning) -> None:
    """Add the program routes to `app` (server.py's build_app calls this once)."""
    routes = _Routes(api, signing)
    app.router.add_post(f"{API_PREFIX}/program", routes.download)
    app.router.add_get(f"{API_PREFIX}/program", routes.upload)


def _taken(reply: CommandReply | Record) -> bool:
    """The PLC took the download, or may still (a pending reply: applied before its deadline
    or never; counted as taken, so that a late one never leaves the running version low)."""
    if isinstance(reply, CommandReply):
        return reply.ok
    return reply.outcome in (Outcome.APPLIED, Outcome.PENDING)


def unprintable(text: str, name: str) -> list[str]:
    """Problems for characters no YAML may contain, found before the scan process sees them."""
    problems = []
    for match in itertools.islice(_NOT_YAML.finditer(text), 20):
        line = text.count("\n", 0, match.start()) + 1
        problems.append(f"{name}:{line}: character U+{ord(match.group()):04X} is not allowed "
                        "in YAML")
    return problems


class _Routes:
    def __init__(self, api: ApiService, signing: DownloadSigning) -> None:
        self._api = api
        self._signing = signing

    async def download(self, request: web.Request) -> web.Response:
        online = flag(request.query.get("online", request.headers.get("X-Softplc-Online")),
                      "online")
        replace = flag(request.query.get("replace"), "replace")
        dry_run = flag(request.query.get("dry_run"), "dry_run")
        allow_older = flag(request.query.get("allow_older"), "allow_older")
        name = request.query.get("name")
        if name is not None and not _NAME.fullmatch(name):
            raise ApiProblem(400, "name must be a plain file name (letters, digits, . _ -)")
        body = await request.read()
        signature = request.headers.get(SIGNATURE_HEADER)
        # The exact bytes, before anything else reads them: nothing unsigned reaches a parser,
        # and no signed version older than the running one unless allowed.
        # One signed download at a time at every door: its version checked and advanced as one.
        async with self._signing.turn(None if dry_run else signature):
            signer = await self._signing.check(body, signature, allow_older)
            if signer is None:
                reply = await self._send(request, body, name, (online, replace, dry_run))
                return self._answer(reply, None, None)
            if not dry_run:
                await self._signing.remember(body, signer)
            reply = await self._send(request, body, name, (online, replace, dry_run))
            note = ""
            if signature and not dry_run and _taken(reply):
                note = await self._signing.applied(body, signature, signer, allow_older)
            return self._answer(reply, signer, f"signed by {signer}{note}")

    async def _send(self, request: web.Request, body: bytes, name: str | None,
                    flags: tuple[bool, bool, bool]) -> CommandReply | Record:
        online, replace, dry_run = flags
        if request.content_type == bundles.CONTENT_TYPE or bundles.is_bundle(body):
            try:  # checked here, so that a bad archive never reaches the scan process
                bundle = await asyncio.to_thread(bundles.unpack, body)
            except bundles.BundleError as exc:
                raise ApiProblem(422, f"{DOWNLOAD_REFUSED}: unusable bundle", [str(exc)]) from None
            return await self._api.command(Command.DOWNLOAD, None, bundle.program, online,
                                           idempotency_key(request), replace=replace,
                                           bundle=body, dry_run=dry_run)
        try:
            text = body.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ApiProblem(400, f"the program must be UTF-8 text ({exc.reason} at byte "
                                  f"{exc.start})") from None
        if not text.strip():
            raise ApiProblem(422, f"{DOWNLOAD_REFUSED}: empty program",
                             [f"{name or 'program'}:1: the request body holds no program"])
        if problems := unprintable(text, name or "program"):
            raise ApiProblem(422, f"{DOWNLOAD_REFUSED}: not YAML text", problems)
        return await self._api.command(Command.DOWNLOAD, text, name, online,
                                       idempotency_key(request), replace=replace,
                                       dry_run=dry_run)

    def _answer(self, reply: CommandReply | Record, signer: str | None,
                signed: str | None) -> web.Response:
        if isinstance(reply, CommandReply) and reply.refusal is not None \
                and reply.refusal.of_program:
            raise ApiProblem(422, reply.message.partition("\n")[0].rstrip(":"),
                             list(reply.problems), state=reply.state.name, id=reply.id,
                             refusal=reply.refusal.value)
        if isinstance(reply, CommandReply) and reply.ok and reply.detail is not None:
            return web.json_response({"ok": True, "message": reply.message, "id": reply.id,
                                      "state": reply.state.name, "plan": reply.detail,
                                      "signer": signer})
        response = self._api.answer(reply)
        if signed is not None and response.status == 200 and isinstance(response.body, bytes):
            # In the answer and so in the audit record's message: who signed what was applied,
            # its version, and a rollback an engineer allowed.
            answer = json.loads(response.body)
            answer["signer"] = signer
            answer["message"] = f"{answer.get('message') or 'download'} ({signed})"
            return web.json_response(answer, headers={
                k: v for k, v in response.headers.items() if k == "Location"})
        return response

    async def upload(self, request: web.Request) -> web.Response:
        """The running program's bundle, byte for byte as it was downloaded."""
        state_dir = self._api.state_dir
        try:
            program = await asyncio.to_thread(boot.load, state_dir)
        except boot.BootUnreadable as exc:
            raise ApiProblem(409, f"no program to upload: {exc}") from None
        running = (await self._api.board_document()).get("program_hash")
        if program is None or program.bundle is None or not running:
            raise ApiProblem(404, "no program to upload: the PLC runs none, or its program "
                             f"came without a bundle (state directory {state_dir})")
        if program.program_hash and program.program_hash != running:
            raise ApiProblem(409, "the running program's bundle is not stored yet (the last "
                             "accepted download is being written); try again", headers={
                                 "Retry-After": "1"})
        return web.Response(body=program.bundle, content_type=bundles.CONTENT_TYPE, headers={
            "Content-Disposition": f'attachment; filename="{Path(program.filename).stem}.zip"'})
