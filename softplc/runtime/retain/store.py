"""The retain files of one state directory: written so that they cannot lie.

Owns: the snapshot file format (a header line with format version, length and sha256, then the
JSON payload), the checked write (every write's count, fsync, close, rename and the directory's
fsync; a short write is continued, a write of 0 bytes or any OSError fails it), the read-back
of the new file before any older one is deleted, keeping the last KEEP valid snapshots,
removing temporaries (at open and after a failed write), the state directory's lock and its
mode (0700), and the file layer (FileOps) through which all of it goes, so a test can inject
faults.
Does not know: what a payload means (runtime/retain/writer.py), threads, scan timing.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import fcntl
import hashlib
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softplc.core.errors import SoftplcError
from softplc.core.jsonparts import pieces

FORMAT = 1
PREFIX, SUFFIX = "retain-", ".json"
LOCK_FILE = "lock"
KEEP = 2  # a crash or a failed write of the newest leaves the one before it valid
READ_CHUNK = 1 << 20


class StateDirBusy(SoftplcError, RuntimeError):
    """Another live runtime holds the state directory's lock."""


class SnapshotInvalid(SoftplcError, ValueError):
    """A snapshot file that is partial, corrupt or of an unknown format."""


class Stage(enum.Enum):
    """Where a snapshot write failed: the status counts errors by stage."""

    ENCODE = "encode"  # the payload is not JSON (a value the runtime should not carry)
    WRITE = "write"  # open/write of the temporary: ENOSPC, EIO, a write of 0 bytes
    FSYNC = "fsync"  # fsync or close of the temporary (delayed write errors surface here)
    VERIFY = "verify"  # the file read back is not the bytes written
    RENAME = "rename"  # rename into place, or the directory's fsync
    OTHER = "other"  # anything else (a bug): counted, and the writer goes on


class WriteFailed(SoftplcError, OSError):
    """A snapshot that is not on disk; `stage` says where it failed. Nothing older was
    deleted, the temporary was removed."""

    def __init__(self, stage: Stage, message: str, code: int = 0) -> None:
        super().__init__(code, message)
        self.stage = stage
        self.message = message

    def __str__(self) -> str:
        return f"{self.stage.value}: {self.message}"


class FileOps:
    """The file system calls of the store. Tests subclass it to fail a call (ENOSPC, a short
    write, EIO at fsync, a failed rename, a flipped byte) where a real disk would."""

    def open(self, path: Path, flags: int, mode: int = 0o600) -> int:
        return os.open(path, flags, mode)

    def write(self, fd: int, data: memoryview) -> int:
        return os.write(fd, data)

    def fsync(self, fd: int) -> None:
        os.fsync(fd)

    def close(self, fd: int) -> None:
        os.close(fd)

    def read(self, fd: int, size: int) -> bytes:
        return os.read(fd, size)

    def replace(self, src: Path, dst: Path) -> None:
        os.replace(src, dst)

    def unlink(self, path: Path) -> None:
        os.unlink(path)


def to_bytes(payload: dict[str, Any]) -> bytes:
    # In pieces (core/jsonparts.py): the writer thread must not hold the scan's interpreter
    # lock for the whole document (one call for a 10,000-place net: ~2.4 ms).
    body = "".join(pieces(payload)).encode()
    header = json.dumps({"format": FORMAT, "length": len(body),
                         "sha256": hashlib.sha256(body).hexdigest()}, sort_keys=True)
    return header.encode() + b"\n" + body


def from_bytes(data: bytes) -> dict[str, Any]:
    """The payload of a snapshot file. Raises SnapshotInvalid saying what is wrong."""
    head, sep, body = data.partition(b"\n")
    if not sep:
        raise SnapshotInvalid("no header line (partial file)")
    try:
        header = json.loads(head)
    except ValueError:
        raise SnapshotInvalid("unreadable header") from None
    if not isinstance(header, dict):
        raise SnapshotInvalid("unreadable header")
    if header.get("format") != FORMAT:
        raise SnapshotInvalid(f"unknown format {header.get('format')!r}")
    if header.get("length") != len(body):
        raise SnapshotInvalid(f"length {len(body)} instead of {header.get('length')} "
                              "(partial file)")
    if hashlib.sha256(body).hexdigest() != header.get("sha256"):
        raise SnapshotInvalid("checksum mismatch")
    payload = json.loads(body)
    if not isinstance(payload, dict) or not isinstance(payload.get("program_hash"), str):
        raise SnapshotInvalid("payload without a program hash")
    return payload


@dataclass(frozen=True, slots=True)
class Loaded:
    path: Path
    payload: dict[str, Any]


def _seq(path: Path) -> int:
    stem = path.name[len(PREFIX):-len(SUFFIX)]
    return int(stem) if stem.isdigit() else -1


def _why(exc: OSError) -> str:
    name = errno.errorcode.get(exc.errno or 0, type(exc).__name__)
    return f"{name}: {exc.strerror or exc}"


class RetainStore:
    """The snapshot files of one state directory, locked for this process while open."""

    def __init__(self, directory: Path, lock_fd: int, keep: int = KEEP,
                 ops: FileOps | None = None) -> None:
        self.directory = directory
        self._lock_fd = lock_fd
        self.keep = max(1, keep)
        self.ops = ops or FileOps()
        self.seq = max((_seq(p) for p in self.files()), default=0)
        self.temps_removed = 0
        self.cleanup_errors = 0
        self.dir_note = ""  # why the directory is not private (0700), if it is not

    @classmethod
    def open(cls, directory: Path | str, keep: int = KEEP,
             ops: FileOps | None = None) -> RetainStore:
        """Lock `directory` (created if missing) and remove temp files of a killed writer.
        Raises StateDirBusy if a live process holds it; a dead one's lock is gone with it."""
        path = Path(directory)
        note = secure_state_dir(path)
        fd = lock_state_dir(path)
        store = cls(path, fd, keep, ops)
        store.dir_note = note
        store.remove_temporaries()
        return store

    def files(self) -> list[Path]:
        """Snapshot files, newest first."""
        found = [p for p in self.directory.glob(f"{PREFIX}*{SUFFIX}") if _seq(p) >= 0]
        return sorted(found, key=_seq, reverse=True)

    def remove_temporaries(self) -> None:
        """Half-written files (of a killed run, or of a failed write): never a snapshot."""
        for tmp in self.directory.glob(f".{PREFIX}*.tmp"):
            self._discard(tmp)

    def _discard(self, path: Path) -> None:
        try:
            self.ops.unlink(path)
            self.temps_removed += 1
        except FileNotFoundError:
            pass
        except OSError:
            self.cleanup_errors += 1  # retried at the next open or failure

    # -- the checked write --------------------------------------------------------------

    def write(self, payload: dict[str, Any]) -> Path:
        """Put `payload` on disk as the next snapshot and prune the old ones. Raises
        WriteFailed (nothing older deleted, temporary removed) unless the new file was
        written whole, synced, read back identical and renamed into place."""
        try:
            data = to_bytes(payload)
        except (TypeError, ValueError) as exc:
            raise WriteFailed(Stage.ENCODE, f"{type(exc).__name__}: {exc}") from None
        seq = max(self.seq, int(payload["seq"]))
        final = self.directory / f"{PREFIX}{seq:09d}{SUFFIX}"
        tmp = self.directory / f".{final.name}.{os.getpid()}.tmp"
        try:
            self._write_file(tmp, data)
            self._verify(tmp, data)
            self._rename(tmp, final)
        except WriteFailed:
            self._discard(tmp)
            self.remove_temporaries()  # and any a previous failure could not remove
            raise
        self.seq = seq
        try:
            self._verify(final, data)
        except WriteFailed:
            self._discard(final)  # the older snapshots remain the newest valid ones
            raise
        self.prune(final)
        return final

    def _write_file(self, path: Path, data: bytes) -> None:
        ops = self.ops
        try:
            fd = ops.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        except OSError as exc:
            raise WriteFailed(Stage.WRITE, f"open {path.name}: {_why(exc)}", exc.errno or 0) \
                from None
        stage, closed = Stage.WRITE, False
        try:
            view, done = memoryview(data), 0
            while done < len(data):  # a short write is legal: write the rest
                n = ops.write(fd, view[done:])
                if n <= 0:
                    raise WriteFailed(Stage.WRITE, f"short write: {done} of {len(data)} "
                                      f"bytes, then {n}", errno.EIO)
                done += n
            stage = Stage.FSYNC
            ops.fsync(fd)
            closed = True
            ops.close(fd)  # a delayed write error (NFS, some FUSE) surfaces here
        except OSError as exc:
            if isinstance(exc, WriteFailed):
                raise
            raise WriteFailed(stage, f"{stage.value} {path.name} after "
                              f"{done} of {len(data)} bytes: {_why(exc)}", exc.errno or 0) \
                from None
        finally:
            if not closed:
                with contextlib.suppress(OSError):
                    ops.close(fd)

    def _read(self, path: Path) -> bytes:
        fd = self.ops.open(path, os.O_RDONLY)
        try:
            chunks = []
            while chunk := self.ops.read(fd, READ_CHUNK):
                chunks.append(chunk)
            return b"".join(chunks)
        finally:
            self.ops.close(fd)

    def _verify(self, path: Path, data: bytes) -> None:
        try:
            back = self._read(path)
        except OSError as exc:
            raise WriteFailed(Stage.VERIFY, f"read back {path.name}: {_why(exc)}",
                              exc.errno or 0) from None
        if back != data:
            why = "checksum mismatch"
            try:
                from_bytes(back)
            except SnapshotInvalid as exc:
                why = str(exc)
            raise WriteFailed(Stage.VERIFY, f"{path.name} read back is not what was written "
                              f"({len(back)} of {len(data)} bytes; {why})", errno.EIO)

    def _rename(self, tmp: Path, final: Path) -> None:
        try:
            self.ops.replace(tmp, final)
        except OSError as exc:
            raise WriteFailed(Stage.RENAME, f"rename to {final.name}: {_why(exc)}",
                              exc.errno or 0) from None
        try:
            self._fsync_dir()  # the rename itself must survive a power loss
        except OSError as exc:
            # The file is in place and complete; whether the rename is durable is not known.
            raise WriteFailed(Stage.RENAME, f"fsync of {self.directory} after the rename to "
                              f"{final.name}: {_why(exc)}", exc.errno or 0) from None

    def _fsync_dir(self) -> None:
        fd = self.ops.open(self.directory, os.O_RDONLY)
        try:
            self.ops.fsync(fd)
        finally:
            self.ops.close(fd)

    def prune(self, newest: Path) -> None:
        """Keep the newest `keep` snapshots that read back valid (each re-read now, so a file
        damaged since it was written does not count); delete the others. Never deletes
        anything unless `newest` is among the valid ones."""
        valid: list[Path] = []
        doomed: list[Path] = []
        for path in self.files():
            if len(valid) < self.keep and self._valid(path):
                valid.append(path)
            else:
                doomed.append(path)
        if newest not in valid:
            return
        for path in doomed:
            self._discard_snapshot(path)

    def _valid(self, path: Path) -> bool:
        try:
            from_bytes(self._read(path))
        except (OSError, SnapshotInvalid, ValueError):
            return False
        return True

    def _discard_snapshot(self, path: Path) -> None:
        try:
            self.ops.unlink(path)
        except FileNotFoundError:
            pass
        except OSError:
            self.cleanup_errors += 1

    # -- reading ------------------------------------------------------------------------

    def load_newest(self) -> tuple[Loaded | None, list[str]]:
        """The newest valid snapshot, and why each newer one was skipped."""
        problems: list[str] = []
        for path in self.files():
            try:
                return Loaded(path, from_bytes(path.read_bytes())), problems
            except (OSError, SnapshotInvalid, ValueError) as exc:
                problems.append(f"snapshot {path}: {exc}")
        return None, problems

    def close(self) -> None:
        if self._lock_fd >= 0:
            os.close(self._lock_fd)  # releases the flock
            self._lock_fd = -1


def lock_state_dir(directory: Path) -> int:
    """flock on DIR/lock, held until the fd is closed (or the process dies, even by SIGKILL:
    a stale lock file never blocks). Returns the fd; raises StateDirBusy naming the holder."""
    fd = os.open(directory / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise StateDirBusy(f"state directory {directory} is in use by another softplc "
                           f"(pid {holder}); give each runtime its own --state-dir") from None
    with contextlib.suppress(OSError):  # the pid is for a person; a full disk keeps the lock
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def secure_state_dir(directory: Path) -> str:
    """Create `directory` with mode 0700, or tighten an existing one of this user's to 0700:
    it holds the API token and the program's state (docs/retain.md). Returns "" when it is
    private, else why not (shown in status and on stderr). Raises OSError if it cannot be
    created."""
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    info = directory.stat()
    mode = stat.S_IMODE(info.st_mode)
    if not mode & 0o077:
        return ""
    if info.st_uid != os.geteuid():
        return (f"state directory {directory} is mode {mode:04o} and owned by uid "
                f"{info.st_uid}, not by this user (uid {os.geteuid()}): not tightened to "
                "0700; others may read its API token and snapshots")
    try:
        os.chmod(directory, 0o700)
    except OSError as exc:
        return (f"state directory {directory} is mode {mode:04o} and could not be tightened "
                f"to 0700 ({_why(exc)}); others may read its API token and snapshots")
    return ""


def check_state_dir(directory: Path | str) -> str:
    """Raise StateDirBusy if another live runtime uses `directory` (lock taken and released).
    Creates it private (secure_state_dir) and returns the note if it is not; a directory
    that cannot be created is left to the caller's own check."""
    path = Path(directory)
    try:
        note = secure_state_dir(path)
    except OSError:
        return ""
    os.close(lock_state_dir(path))
    return note
