"""Signed downloads in the HTTP service: refused before they reach the scan process unless a
trusted key signed the exact bytes, and the signer of the running program for status.

Owns: the service's trusted keys (read again when their directory changes: a key added or
removed acts at the next download), the check (`SIGNATURE_HEADER`, 422 with the reason and
`refusal: "signature"`), and the signers of accepted bodies in STATE_DIR/signers.json
(SHA-256 of the body -> the key's name), which status matches against the boot program: so
a warm start or a restarted scan process of a kept program still names its signer.
Does not know: Ed25519 (security/signing.py), the scan, routes.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import json
import logging
from pathlib import Path
from typing import Any, Final

from softplc.api.problems import ApiProblem
from softplc.core.snapshot import Refusal
from softplc.program import boot
from softplc.security.files import write_private
from softplc.security.signing import SignatureRefused, TrustedKeys

log = logging.getLogger(__name__)

SIGNATURE_HEADER: Final = "X-Softplc-Signature"
SIGNERS_FILE: Final = "signers.json"
KEEP: Final = 64  # signed bodies remembered; the running one is the newest but a few


class DownloadSigning:
    def __init__(self, state_dir: Path, trusted_dir: Path) -> None:
        self.state_dir = Path(state_dir)
        self.trusted_dir = Path(trusted_dir)
        self._keys = TrustedKeys()
        self._seen: tuple[int, int] | None = None
        self._running: tuple[Any, str | None] = (None, None)  # (boot file's stat, signer)

    def trusted(self) -> TrustedKeys:
        try:
            info = self.trusted_dir.stat()
            seen: tuple[int, int] | None = (info.st_ino, info.st_mtime_ns)
        except OSError:
            seen = None
        if seen != self._seen:
            self._keys = TrustedKeys.load(self.trusted_dir) if seen else TrustedKeys()
            self._seen = seen
            for problem in self._keys.problems:
                log.warning("trusted key skipped: %s", problem)
        return self._keys

    async def check(self, body: bytes, signature: str | None) -> str | None:
        """The signer's name; None when no key is trusted (signatures are not asked for).
        Raises 422 when keys are trusted and none of them signed `body`."""
        keys = self.trusted()
        if not keys.keys:
            return None
        try:
            return await asyncio.to_thread(keys.verify, body, signature)
        except SignatureRefused as exc:
            raise ApiProblem(422, exc.reason, refusal=Refusal.SIGNATURE.value) from None

    async def remember(self, body: bytes, signer: str) -> None:
        """Record that `signer` signed `body` (before it is sent: status never finds the
        program running without its record)."""
        await asyncio.to_thread(self._remember, hashlib.sha256(body).hexdigest(), signer)

    def _remember(self, digest: str, signer: str) -> None:
        signers = {k: v for k, v in self._signers().items() if k != digest}
        signers[digest] = signer
        data = json.dumps(dict(list(signers.items())[-KEEP:]), indent=0).encode()
        write_private(self.state_dir / SIGNERS_FILE, data)

    def _signers(self) -> dict[str, str]:
        with contextlib.suppress(OSError, ValueError):
            data = json.loads((self.state_dir / SIGNERS_FILE).read_text(encoding="utf-8"))
            if isinstance(data, dict):
                return {str(k): str(v) for k, v in data.items()}
        return {}

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
                signer = self._signers().get(hashlib.sha256(body).hexdigest())
        self._running = (key, signer)
        return signer
