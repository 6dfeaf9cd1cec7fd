"""Signed downloads in the HTTP service: the HTTP door of security/programgate.py, and the
signer of the running program for status.

Owns: the header (`SIGNATURE_HEADER`), turning the gate's refusal into 422 with the reason
and `refusal: "signature"`, telling the gate what the PLC took (its version runs), and
matching the boot program against the signers the gate kept (so a warm start or a restarted
scan process of a kept program still names its signer).
Does not know: Ed25519, trusted keys (the gate decides), the scan, routes.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, Final

from softplc.api.problems import ApiProblem
from softplc.core.snapshot import Refusal
from softplc.program import boot
from softplc.security.programgate import SIGNERS_FILE, KeysSeen, ProgramGate, ProgramRefused

SIGNATURE_HEADER: Final = "X-Softplc-Signature"


class DownloadSigning:
    def __init__(self, state_dir: Path, trusted_dir: Path, required: bool = False) -> None:
        self.state_dir = Path(state_dir)
        self.gate = ProgramGate(state_dir, trusted_dir, required)
        self._running: tuple[Any, str | None] = (None, None)  # (boot file's stat, signer)

    def keys(self) -> KeysSeen:
        """For status: read again only when the directory changed (gate.status_keys)."""
        return self.gate.status_keys()

    @contextlib.asynccontextmanager
    async def turn(self, signature: str | None) -> AsyncIterator[None]:
        """The gate's turn (one signed download at a time at every door); 422 when it does
        not come."""
        try:
            async with self.gate.turn(signature):
                yield
        except ProgramRefused as exc:
            raise ApiProblem(422, exc.reason, refusal=Refusal.SIGNATURE.value) from None

    async def check(self, body: bytes, signature: str | None,
                    allow_older: bool = False) -> str | None:
        """The signer's name; None when signatures are not required. Raises 422 when the
        gate refuses `body` (unsigned, not trusted, or older than the running version and
        not `allow_older`)."""
        try:
            return await asyncio.to_thread(self.gate.admit, body, signature, allow_older)
        except ProgramRefused as exc:
            raise ApiProblem(422, exc.reason, refusal=Refusal.SIGNATURE.value) from None

    async def remember(self, body: bytes, signer: str) -> None:
        await asyncio.to_thread(self.gate.remember, body, signer)

    async def applied(self, body: bytes, signature: str, signer: str,
                      allow_older: bool) -> str:
        """The PLC took `body`: its signed version runs now (the gate's `applied`)."""
        return await asyncio.to_thread(self.gate.applied, body, signature, signer,
                                       allow_older)

    async def running_signer(self, program_hash: str | None) -> str | None:
        """Who signed the running program (`program_hash`): None when unsigned, unknown, or
        not yet kept as the boot program (a download being stored)."""
        if not program_hash:
            return None
        return await asyncio.to_thread(self._running_signer, program_hash)

    def _running_signer(self, program_hash: str) -> str | None:
        try:
            stats = [(p.st_ino, p.st_mtime_ns, p.st_size) for p in (
                (self.state_dir / boot.BOOT_FILE).stat(),
                (self.state_dir / SIGNERS_FILE).stat())]
        except OSError:
            return None
        key = (stats, program_hash)
        if self._running[0] == key:  # the boot file is up to 1.4 MB: read once per change
            return self._running[1]
        signer = None
        with contextlib.suppress(boot.BootUnreadable):
            program = boot.load(self.state_dir)
            if program is not None and program.program_hash == program_hash:
                body = program.bundle if program.bundle is not None \
                    else program.text.encode("utf-8")
                signer = self.gate.signers().get(hashlib.sha256(body).hexdigest())
        self._running = (key, signer)
        return signer
