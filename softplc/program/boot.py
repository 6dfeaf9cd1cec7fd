"""The boot program: the last program the PLC accepted, kept in the state directory.

Owns: writing the accepted program's source (its text, the name it was downloaded under, the
directory its relative `io_image:`/subnet paths resolve against, and its bundle: the program
with its io image and subnets as they were downloaded, for `softplc upload`) atomically
beside the retain snapshots, and reading it back for `softplc run` without a program argument and
for a scan process the supervisor restarts. Does not know: compiling, the scan, retain snapshots.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

from softplc.core.errors import SoftplcError
from softplc.program import bundle as bundles

BOOT_FILE: Final = "boot_program.json"
FORMAT: Final = 1


class BootUnreadable(SoftplcError, ValueError):
    """The boot program file exists but cannot be used (truncated, edited, wrong format)."""


@dataclass(frozen=True, slots=True)
class BootProgram:
    """`filename` names the program in messages and anchors its relative paths; `root`
    bounds where they may lead (None: anywhere, as for a program on the command line)."""

    filename: str
    text: str
    root: str | None
    bundle: bytes | None = None  # the zip of softplc/program/bundle.py, byte for byte
    program_hash: str = ""  # of the net compiled from it: is it the one running?

    def describe(self) -> str:
        return f"boot program {Path(self.filename).name} (last accepted)"


def save(state_dir: str | Path, program: BootProgram) -> None:
    """Write atomically: a crash leaves the previous boot program or the new one, never half."""
    commit(stage(state_dir, program))


def stage(state_dir: str | Path, program: BootProgram, encoded: bytes | None = None) -> Path:
    """Write `program` beside the boot program, flushed to the disk, not yet in force: what
    can fail (a full or read-only disk) fails here. `commit` puts it in force, `unstage`
    drops it. `encoded`: its file as `encode` made it, elsewhere (the compile process)."""
    directory = Path(state_dir)
    directory.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".boot-", dir=directory)
    try:
        with os.fdopen(fd, "wb") as out:
            for piece in _json_pieces(program) if encoded is None else (encoded,):
                out.write(piece)
            out.flush()
            os.fsync(out.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return Path(tmp)


def encode(program: BootProgram) -> bytes:
    """The boot file of `program`, as `stage` writes it."""
    return b"".join(_json_pieces(program))


_PIECE: Final = 1 << 15  # characters of text, bytes of bundle (a multiple of 3) per piece


def _json_pieces(program: BootProgram) -> Iterator[bytes]:
    """The boot file's JSON a piece at a time: the download thread writes it while the scan
    runs, and each piece holds the interpreter lock for tens of microseconds (json.dumps of a
    500 KB program held it 1-5 ms in one C call, base64 of a 4 MiB bundle longer). The same
    JSON text as json.dumps of the whole: strings are escaped per character, base64 per
    3 bytes, so pieces cut there join into the whole."""
    head = {"format": FORMAT, "filename": program.filename, "root": program.root,
            "program_hash": program.program_hash}
    yield json.dumps(head)[:-1].encode() + b', "text": "'
    text = program.text
    for start in range(0, len(text), _PIECE):
        yield json.dumps(text[start:start + _PIECE])[1:-1].encode()
    packed = program.bundle
    if packed is None:
        yield b'", "bundle": null}'
        return
    yield b'", "bundle": "'
    for start in range(0, len(packed), _PIECE - _PIECE % 3):
        yield base64.b64encode(packed[start:start + _PIECE - _PIECE % 3])
    yield b'"}'


def commit(staged: Path) -> None:
    """The staged program becomes the boot program: one rename, atomic."""
    os.replace(staged, staged.parent / BOOT_FILE)


def unstage(staged: Path) -> None:
    staged.unlink(missing_ok=True)


def load(state_dir: str | Path) -> BootProgram | None:
    """The boot program, None when there is none; BootUnreadable when it cannot be used."""
    path = Path(state_dir) / BOOT_FILE
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise BootUnreadable(f"{path}: {exc.strerror}") from None
    try:
        data = json.loads(raw)
        if data.get("format") != FORMAT:
            raise BootUnreadable(f"{path}: format {data.get('format')!r}, expected {FORMAT}")
        root = data["root"]
        packed = data.get("bundle")  # absent in files written before bundles
        return BootProgram(str(data["filename"]), str(data["text"]),
                           None if root is None else str(root),
                           None if packed is None else base64.b64decode(packed, validate=True),
                           str(data.get("program_hash") or ""))
    except (ValueError, KeyError, TypeError, AttributeError, binascii.Error) as exc:
        if isinstance(exc, BootUnreadable):
            raise
        raise BootUnreadable(f"{path}: not a boot program file ({exc})") from None


def from_file(path: str | Path, program_hash: str = "") -> BootProgram:
    """The boot program for a program file given on the command line, with its bundle (so
    that `softplc upload` works for it too; None when its files exceed a bundle's limits)."""
    resolved = Path(path).resolve()
    try:
        packed: bytes | None = bundles.pack(bundles.from_files(resolved))
    except bundles.BundleError:
        packed = None
    text = Path(bundles.file_of(resolved)).read_text(encoding="utf-8")  # FILE.xml#POU too
    return BootProgram(str(resolved), text, None, packed,
                       program_hash)
