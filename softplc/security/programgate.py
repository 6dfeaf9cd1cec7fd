"""The one decision point of "may this program be loaded", for every door that downloads
(HTTP `POST /program`, OPC UA `Download`, and any door added later: tests/security/test_doors.py).

Owns: the PLC's trusted keys as their directory holds them *now* (compared by content: a key
replaced in place, added or removed acts at the next download), whether signatures are
required (fail closed: once `--trusted-keys` was given or a trusted key was seen, a directory
that becomes empty or unreadable refuses every download, says so in status and logs it once
per change), the check of the exact bytes before anything parses them, the rollback rule (a
signed version older than the running one is refused unless an engineer allows it; the
version file is versions.py's), and the signers of accepted bodies in STATE_DIR/signers.json
(SHA-256 of the body -> the key's name, the last KEEP), which status matches against the
running program; the turn (`turn`: one signed download at a time across doors and processes,
so that checking the running version and advancing it are one decision).
Does not know: HTTP, OPC UA, the scan, Ed25519 (signing.py), how a program is parsed.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import hashlib
import json
import logging
import os
import threading
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from softplc.core.errors import SoftplcError
from softplc.core.snapshot import DOWNLOAD_REFUSED
from softplc.security import versions
from softplc.security.files import write_private
from softplc.security.signing import (
    MAX_KEYS,
    Signature,
    SignatureRefused,
    SigningError,
    TrustedKeys,
)

log = logging.getLogger(__name__)

SIGNERS_FILE: Final = "signers.json"
TURN_FILE: Final = "signed_version.lock"
TURN_WAIT_S: Final = 30.0  # a signed download waits this long for another one to be taken
_TURN_POLL_S: Final = 0.02
KEEP: Final = 64  # signed bodies remembered; the running one is the newest but a few


class ProgramRefused(SoftplcError):
    """A download no trusted key allows; `reason` is one line for the client."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class KeysSeen:
    """The trusted keys as last read: `digest` of the directory's content, `problem` why
    none could be used while signatures are required (status shows it)."""

    keys: TrustedKeys
    digest: str
    required: bool
    problem: str | None = None

    def status(self) -> dict[str, object]:
        return {"required": self.required, "trusted": self.keys.names,
                "problem": self.problem}


class ProgramGate:
    """The trusted keys of one PLC (`trusted_dir`); `required` from the start when the
    directory was named on the command line (`--trusted-keys`)."""

    def __init__(self, state_dir: Path, trusted_dir: Path, required: bool = False) -> None:
        self.state_dir = Path(state_dir)
        self.trusted_dir = Path(trusted_dir)
        self._lock = threading.Lock()
        self._seen = KeysSeen(TrustedKeys(), "", required)
        self._stamp: tuple[object, ...] | None = None  # the directory as status last saw it

    def keys(self) -> KeysSeen:
        """The keys as the directory holds them now (read at every call: a few small files)."""
        digest, files = _content(self.trusted_dir)
        with self._lock:
            if digest == self._seen.digest:
                return self._seen
            keys = TrustedKeys.load(self.trusted_dir) if files else TrustedKeys()
            required = self._seen.required or bool(keys.keys)
            problem = None
            if required and not keys.keys:
                problem = (f"no trusted key can be read in {self.trusted_dir} "
                           f"({'unreadable' if files is None else 'none there'}): every "
                           "download is refused until a key is trusted again (softplc keys "
                           "trust) or the PLC is restarted without trusted keys")
                log.error("signed downloads: %s", problem)
            for skipped in keys.problems:
                log.warning("trusted key skipped: %s", skipped)
            if keys.keys:
                log.info("signed downloads: trusted keys %s (%s)", ", ".join(keys.names),
                         self.trusted_dir)
            self._seen = KeysSeen(keys, digest, required, problem)
            return self._seen

    def status_keys(self) -> KeysSeen:
        """The keys for status (every GET /status): read again only when the directory's
        stat or one of its key files' stat changed (a key added, removed, or written in
        place shows at the next request), else as last seen; a download reads them by
        content whatever their stats say (`keys`)."""
        stamp = _stamp(self.trusted_dir)
        with self._lock:
            if stamp is not None and stamp == self._stamp:
                return self._seen
        seen = self.keys()
        with self._lock:
            self._stamp = stamp
        return seen

    def admit(self, body: bytes, signature: str | None, allow_older: bool = False) -> str | None:
        """The signer's name, or None when signatures are not required. Raises
        ProgramRefused when they are and no trusted key signed `body` (or none is left), or
        when its signed version is older than the running one and not `allow_older` (an
        engineer's rollback). Blocking (reads the directory, verifies): call it in a thread
        from a loop."""
        seen = self.keys()
        if seen.problem is not None:
            raise ProgramRefused(f"{DOWNLOAD_REFUSED}: {seen.problem}")
        if not seen.keys.keys:
            return None
        try:
            signed = seen.keys.verify(body, signature)
        except SignatureRefused as exc:
            raise ProgramRefused(exc.reason) from None
        running = versions.read(self.state_dir)
        digest = hashlib.sha256(body).hexdigest()
        if reason := versions.refusal(running, signed.version, allow_older, digest):
            raise ProgramRefused(reason)
        return signed.signer

    @contextlib.asynccontextmanager
    async def turn(self, signature: str | None) -> AsyncIterator[None]:
        """One signed download at a time, at every door and in every process of the PLC
        (flock on STATE_DIR/signed_version.lock): a door holds it from `admit` until `applied`
        or its refusal, so that the check of the running version and its advance are one
        decision (two signed downloads at once both passed the check, and the one applied
        last ran whatever the version file said). Waits at most TURN_WAIT_S, polling: a
        cancelled wait holds nothing. Raises ProgramRefused when the turn does not come.
        Without a signature there is no version to decide: no turn is taken."""
        if not signature:
            yield
            return
        try:
            fd = os.open(self.state_dir / TURN_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC,
                         0o600)
        except OSError as exc:
            raise ProgramRefused(f"{DOWNLOAD_REFUSED}: {self.state_dir / TURN_FILE} cannot be "
                                 f"opened ({exc.strerror or exc}): the running signed version "
                                 "cannot be decided") from None
        try:
            loop = asyncio.get_running_loop()
            deadline_s = loop.time() + TURN_WAIT_S
            while not _locked(fd):
                if loop.time() >= deadline_s:
                    raise ProgramRefused(f"{DOWNLOAD_REFUSED}: another signed download is "
                                         f"being taken (waited {TURN_WAIT_S:g} s): try again")
                await asyncio.sleep(_TURN_POLL_S)
            yield
        finally:
            os.close(fd)  # releases the lock

    def applied(self, body: bytes, signature: str, signer: str,
                allow_older: bool = False) -> str:
        """After the PLC took a download `admit` let through as signed by `signer` (not a dry
        run): its version becomes the running one. Returns what to add to the download's
        message, and so to its audit record (the version, a rollback). Blocking."""
        try:
            version = Signature.parse(signature).version or 0
        except SigningError:
            return ""
        digest = hashlib.sha256(body).hexdigest()
        with self._lock:
            try:
                return versions.applied(self.state_dir, version, signer, digest, allow_older)
            except OSError as exc:
                path = self.state_dir / versions.VERSION_FILE
                log.error("signed downloads: %s cannot be written (%s): version %d is not "
                          "recorded as running", path, exc.strerror or exc, version)
                return f", version {version} (not recorded: {path} cannot be written)"

    def remember(self, body: bytes, signer: str) -> None:
        """Record that `signer` signed `body` (before it is sent: status never finds the
        program running without its record). Blocking."""
        digest = hashlib.sha256(body).hexdigest()
        signers = {k: v for k, v in self.signers().items() if k != digest}
        signers[digest] = signer
        data = json.dumps(dict(list(signers.items())[-KEEP:]), indent=0).encode()
        write_private(self.state_dir / SIGNERS_FILE, data)

    def signers(self) -> dict[str, str]:
        with contextlib.suppress(OSError, ValueError):
            data = json.loads((self.state_dir / SIGNERS_FILE).read_text(encoding="utf-8"))
            if isinstance(data, dict):
                return {str(k): str(v) for k, v in data.items()}
        return {}


def _content(directory: Path) -> tuple[str, list[Path] | None]:
    """A digest of the names and bytes of the `*.pub` files (None: unreadable)."""
    digest = hashlib.sha256()
    try:
        files = sorted(directory.glob("*.pub"))[:MAX_KEYS]
        for path in files:
            digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    except OSError as exc:
        return f"unreadable: {exc.strerror}", None
    return digest.hexdigest(), files


def _stamp(directory: Path) -> tuple[object, ...] | None:
    """The directory's and its `*.pub` files' stats (no file is read); None: unreadable."""
    try:
        info = directory.stat()
        names = sorted(n for n in os.listdir(directory) if n.endswith(".pub"))[:MAX_KEYS]
        files = tuple((n, *_stats((directory / n).stat())) for n in names)
    except OSError:
        return None
    return (*_stats(info), files)


def _stats(info: os.stat_result) -> tuple[int, int, int, int]:
    return info.st_ino, info.st_mtime_ns, info.st_ctime_ns, info.st_size


def _locked(fd: int) -> bool:
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    return True
