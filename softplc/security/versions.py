"""The rollback rule of signed programs: the version of the signed program last applied, kept
in STATE_DIR/signed_version.json, and whether a signed version may be loaded over it.

Owns: the file (0600, written whole and durably: `version`, `body_sha256` (a version names one
program: another one with the running version is refused), and `signer` for a person),
reading it (absent: version 0, nothing versioned applied yet; corrupt or unreadable: unknown,
and then every signed download is refused unless an engineer allows an older one), the rule
(a lower version than the running one is refused unless allowed; the same one for the same
program, or a higher one, is taken) and the one line that says so.
Does not know: signatures (signing.py), trusted keys and doors (programgate.py), HTTP.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

from softplc.core.snapshot import DOWNLOAD_REFUSED
from softplc.security.files import write_private
from softplc.security.signing import MAX_VERSION

VERSION_FILE: Final = "signed_version.json"
_MAX_BYTES: Final = 4096  # the file holds three short fields


@dataclass(frozen=True, slots=True)
class Running:
    """The version of the signed program last applied; `problem` (one line naming the file)
    when the file cannot be read, and so the version is unknown."""

    version: int
    problem: str | None = None
    # of the program that runs with it ("" when not recorded); not the version's identity
    body_sha256: str = field(default="", compare=False)


def read(state_dir: Path) -> Running:
    path = Path(state_dir) / VERSION_FILE
    try:
        with path.open("rb") as handle:
            raw = handle.read(_MAX_BYTES + 1)
    except FileNotFoundError:
        return Running(0)
    except OSError as exc:
        return _unknown(path, f"unreadable ({exc.strerror or exc})")
    if len(raw) > _MAX_BYTES:
        return _unknown(path, f"over {_MAX_BYTES} bytes")
    try:
        data = json.loads(raw)
    except (ValueError, RecursionError):  # UnicodeDecodeError is a ValueError
        return _unknown(path, "not JSON")
    version = data.get("version") if isinstance(data, dict) else None
    if type(version) is not int or not 0 <= version <= MAX_VERSION:
        return _unknown(path, "no version in it")
    body = data.get("body_sha256")
    return Running(version, body_sha256=body if isinstance(body, str) else "")


def _unknown(path: Path, what: str) -> Running:
    return Running(0, f"{path} is {what}: the running signed version is unknown, so a signed "
                   "download is refused unless an engineer allows an older one "
                   "(--allow-older), which writes the file anew")


def refusal(running: Running, version: int, allow_older: bool,
            body_sha256: str = "") -> str | None:
    """Why a program signed with `version` (its body's SHA-256) may not be loaded now; None:
    it may. The running version again is taken for the running program (sent again), not
    for another one: one version names one release."""
    if allow_older:
        return None
    if running.problem is not None:
        return f"{DOWNLOAD_REFUSED}: {running.problem}"
    if version < running.version:
        unversioned = " (signed without --version)" if version == 0 else ""
        return (f"{DOWNLOAD_REFUSED}: signed version {version}{unversioned} is older than the "
                f"running {running.version} (an engineer may pass --allow-older)")
    if version == running.version > 0 and body_sha256 and running.body_sha256 \
            and body_sha256 != running.body_sha256:
        return (f"{DOWNLOAD_REFUSED}: signed version {version} is the running version, of "
                "another program: a new release needs a higher version (an engineer may "
                "pass --allow-older)")
    return None


def applied(state_dir: Path, version: int, signer: str, body_sha256: str,
            allow_older: bool) -> str:
    """Record that the PLC took a program signed with `version`: it becomes the running
    version (never lowered unless `allow_older`). Returns what to add to the download's
    message (and so to its audit record): the version, and a rollback when there was one.
    Raises OSError when the file cannot be written."""
    running = read(state_dir)
    if running.problem is None and version < running.version and not allow_older:
        return f", version {version}"  # a higher one was applied meanwhile: it stays
    data = {"version": version, "signer": signer, "body_sha256": body_sha256}
    write_private(Path(state_dir) / VERSION_FILE, json.dumps(data).encode() + b"\n",
                  sync_directory=True)
    if running.problem is not None:
        return f", version {version} (allow older: the running version was unknown)"
    if version < running.version:
        return f", version {version}, rolled back from {running.version} (allow older)"
    return f", version {version}" if version else ""
