"""Retain and warm restart: the PLC's state in files that survive a crash or a power loss.

Owns: what is retained (marking, coloured tokens, timers, the image's outputs and %M memory,
the lifecycle state, scan count and scan clock, program name and hash; a sim plant's state,
labelled simulation-only), the file format (a header line with format version, length and
sha256, then the JSON payload), the atomic write (temp file, fsync, rename, fsync of the
directory), choosing the newest valid snapshot, the state-directory lock, and the writer thread.
Does not know: scan timing, Modbus, HTTP, other processes than the one holding the lock.

Time across a restart: every timer (enabling delays, three-phase firings, the stop instant)
is kept in scan-clock nanoseconds, and a warm restart continues the scan clock from the
snapshot's scan time (ContinuedClock). Elapsed time is preserved and the downtime does not
count, exactly as when the PLC is stopped and resumed: a 2 s delay with 0.5 s left at the
snapshot has 0.5 s left after the restart. What ran between the last snapshot and the
crash (at most one retain interval) is lost and runs again.
"""

from __future__ import annotations

import base64
import fcntl
import hashlib
import io
import json
import os
import pickle
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from softplc.core.events import EventMemory
from softplc.core.image import AREAS, ProcessImage
from softplc.core.lifecycle import PlcState
from softplc.core.net import Busy, CompiledNet, NetState
from softplc.core.problems import FaultCode
from softplc.core.scan import Plc
from softplc.runtime.clock import Clock
from softplc.runtime.realtime import background_thread

FORMAT = 1
PREFIX, SUFFIX = "retain-", ".json"
LOCK_FILE = "lock"
KEEP = 2  # a crash while writing the newest leaves the one before it valid


class StateDirBusy(RuntimeError):
    """Another live runtime holds the state directory's lock."""


class SnapshotInvalid(ValueError):
    """A snapshot file that is partial, corrupt or of an unknown format."""


# -- capture (scan thread) and encoding (writer thread) ---------------------------------------

@dataclass(frozen=True, slots=True)
class Capture:
    """Copies taken at a scan boundary: consistent, cheap to take, encoded later."""

    net: CompiledNet
    state: PlcState
    fault_code: int
    scan_count: int
    now_ns: int
    net_state: NetState
    image: ProcessImage
    held: tuple[np.ndarray, np.ndarray] | None
    stopped_at_ns: int | None
    events_last: dict[str, int]
    events_armed: dict[str, bool]
    field: dict[str, bytes]  # driver name -> pickled sim plant (simulation only)


def capture(plc: Plc, now_ns: int, plants: dict[str, object]) -> Capture | None:
    """The PLC after the scan at `now_ns`; None when there is no program to retain."""
    if plc.net is None or plc.engine is None:
        return None
    held = None if plc.held is None else (plc.held[0].copy(), plc.held[1].copy())
    return Capture(plc.net, plc.state, plc.fault_code, plc.scan_count, now_ns,
                   plc.engine.state.copy(), plc.image.copy(), held, plc.stopped_at_ns,
                   dict(plc.events.last), dict(plc.events.armed),
                   {name: pickle.dumps(plant) for name, plant in plants.items()})


def encode(cap: Capture, seq: int, wall_ns: int) -> dict[str, Any]:
    net, st = cap.net, cap.net_state
    places, transitions = net.place_names, net.transitions
    return {
        "seq": seq, "written_unix_ns": wall_ns,
        "program": net.name, "program_hash": net.program_hash,
        "state": cap.state.name, "fault_code": cap.fault_code,
        "scan_count": cap.scan_count, "now_ns": cap.now_ns, "stopped_at_ns": cap.stopped_at_ns,
        "marking": {places[p]: int(n) for p, n in enumerate(st.marking)},
        "tokens": {places[p]: [dict(t) for t in toks] for p, toks in st.tokens.items()},
        "enabled_since_ns": {transitions[t].name: ns for t, ns in st.enabled_since.items()},
        "busy": {transitions[t].name: {"end_ns": b.end_ns, "produce": [
            [places[p], n, None if r is None else dict(r)] for p, n, r in b.produce]}
            for t, b in st.busy.items()},
        "image": {area: _pack(getattr(cap.image, area)) for area in AREAS},
        "held": None if cap.held is None else [_pack(a) for a in cap.held],
        "events": {"last": cap.events_last, "armed": cap.events_armed},
        "field_simulation_only": {name: base64.b64encode(blob).decode()
                                  for name, blob in cap.field.items()},
    }


def _pack(values: np.ndarray) -> str:
    """An image area as base64 of its little-endian bytes: 5 k values in microseconds."""
    return base64.b64encode(values.astype(values.dtype.newbyteorder("<")).tobytes()).decode()


def _unpack(text: str, like: np.ndarray) -> np.ndarray:
    values = np.frombuffer(base64.b64decode(text), dtype=like.dtype.newbyteorder("<"))
    if values.shape != like.shape:
        raise SnapshotInvalid(f"image area of {values.size} values instead of {like.size}")
    return values.astype(like.dtype)


def to_bytes(payload: dict[str, Any]) -> bytes:
    body = json.dumps(payload, separators=(",", ":"), sort_keys=True).encode()
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


# -- restore ------------------------------------------------------------------------------

def restore(plc: Plc, payload: dict[str, Any], resume: bool) -> PlcState:
    """Put a snapshot into `plc`, which already holds the same program (downloaded, STOPPED).
    A snapshot taken while RUNNING resumes only if `resume`; otherwise it waits STOPPED with
    its timers frozen at the snapshot instant (`softplc resume` continues it)."""
    net, engine = plc.net, plc.engine
    assert net is not None and engine is not None and net.program_hash == payload["program_hash"]
    places, names = net.place_index, {t.name: t.index for t in net.transitions}
    state = NetState.initial(net)
    state.marking[:] = 0
    for name, count in payload["marking"].items():
        state.marking[places[name]] = count
    state.tokens = {places[name]: list(toks) for name, toks in payload["tokens"].items()}
    state.enabled_since = {names[t]: ns for t, ns in payload["enabled_since_ns"].items()}
    state.busy = {names[t]: Busy(b["end_ns"], tuple((places[p], n, r) for p, n, r in b["produce"]))
                  for t, b in payload["busy"].items()}
    engine.state = state
    engine.invalidate()  # enabledness is recomputed from the restored marking
    for area in AREAS:
        target = getattr(plc.image, area)
        target[:] = _unpack(payload["image"][area], target)
    plc.image.copy_into(plc.prev)
    plc.events = EventMemory(dict(payload["events"]["last"]), dict(payload["events"]["armed"]))
    plc.scan_count = payload["scan_count"]
    plc.fault_code = FaultCode(payload["fault_code"])
    was = PlcState[payload["state"]]
    held = payload["held"]
    plc.held = None if held is None else (_unpack(held[0], plc.image.qx),
                                          _unpack(held[1], plc.image.qw))
    plc.stopped_at_ns = payload["stopped_at_ns"]
    plc.state = was
    if was is PlcState.RUNNING and not resume:
        plc.state = PlcState.STOPPED
        plc.stopped_at_ns = payload["now_ns"]
        plc.held = (plc.image.qx.copy(), plc.image.qw.copy())
    return plc.state


class _PlantUnpickler(pickle.Unpickler):
    """Only plant models and what they are made of: a state file is data, not code."""

    ALLOWED: frozenset[tuple[str, str]] = frozenset({
        ("random", "Random"), ("builtins", "set"), ("builtins", "frozenset"),
        ("copyreg", "_reconstructor"), ("builtins", "object")})

    def find_class(self, module: str, name: str) -> Any:
        if module.startswith("softplc.devices.plants.") or (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not a plant model")


def load_plant(blob: str) -> object:
    return _PlantUnpickler(io.BytesIO(base64.b64decode(blob))).load()


class ContinuedClock:
    """A clock whose time continues from `start_ns` (the snapshot's scan time): the downtime
    between a crash and the restart does not exist for the PLC's timers."""

    __slots__ = ("base", "offset_ns")

    def __init__(self, base: Clock, start_ns: int) -> None:
        self.base = base
        self.offset_ns = start_ns - base.now_ns()

    def now_ns(self) -> int:
        return self.base.now_ns() + self.offset_ns

    def wait_until(self, deadline_ns: int) -> int:
        return self.base.wait_until(deadline_ns - self.offset_ns) + self.offset_ns


# -- the state directory --------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Loaded:
    path: Path
    payload: dict[str, Any]


def _seq(path: Path) -> int:
    stem = path.name[len(PREFIX):-len(SUFFIX)]
    return int(stem) if stem.isdigit() else -1


class RetainStore:
    """The snapshot files of one state directory, locked for this process while open."""

    def __init__(self, directory: Path, lock_fd: int, keep: int = KEEP) -> None:
        self.directory = directory
        self._lock_fd = lock_fd
        self.keep = keep
        self.seq = max((_seq(p) for p in self.files()), default=0)

    @classmethod
    def open(cls, directory: Path | str, keep: int = KEEP) -> RetainStore:
        """Lock `directory` (created if missing) and remove temp files of a killed writer.
        Raises StateDirBusy if a live process holds it; a dead one's lock is gone with it."""
        path = Path(directory)
        path.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd = lock_state_dir(path)
        for tmp in path.glob(f".{PREFIX}*.tmp"):
            tmp.unlink(missing_ok=True)  # half-written by a killed run: never a snapshot
        return cls(path, fd, keep)

    def files(self) -> list[Path]:
        """Snapshot files, newest first."""
        found = [p for p in self.directory.glob(f"{PREFIX}*{SUFFIX}") if _seq(p) >= 0]
        return sorted(found, key=_seq, reverse=True)

    def write(self, payload: dict[str, Any]) -> Path:
        """Atomically: after a crash at any instant the file is absent or complete."""
        self.seq = max(self.seq, int(payload["seq"]))
        final = self.directory / f"{PREFIX}{payload['seq']:09d}{SUFFIX}"
        tmp = self.directory / f".{final.name}.{os.getpid()}.tmp"
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, to_bytes(payload))  # one write: a payload is well under 2 GB
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, final)
        _fsync_dir(self.directory)  # the rename itself must survive a power loss
        for old in self.files()[self.keep:]:
            old.unlink(missing_ok=True)
        return final

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
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


def check_state_dir(directory: Path | str) -> None:
    """Raise StateDirBusy if another live runtime uses `directory` (lock taken and released)."""
    path = Path(directory)
    if path.is_dir():
        os.close(lock_state_dir(path))


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


# -- the decision at start ------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class StartDecision:
    mode: str  # "cold" or "warm"
    reason: str
    snapshot: Loaded | None = None


def decide(store: RetainStore, net: CompiledNet | None) -> StartDecision:
    loaded, problems = store.load_newest()
    skipped = "; ".join(problems)
    if net is None:
        return StartDecision("cold", "no program on the command line")
    if loaded is None:
        return StartDecision("cold", skipped or f"no snapshot in {store.directory}")
    snap_hash = loaded.payload["program_hash"]
    if snap_hash != net.program_hash:
        return StartDecision("cold", f"snapshot {loaded.path.name} program "
                             f"{loaded.payload.get('program')} hash {snap_hash[:12]} differs "
                             f"from program {net.name} hash {net.program_hash[:12]}")
    # Wall-clock age, for a person to read; the scan clock continues regardless.
    age_s = (time.time_ns() - int(loaded.payload.get("written_unix_ns", 0))) / 1e9
    reason = (f"snapshot {loaded.path.name} from scan {loaded.payload['scan_count']}, "
              f"{age_s:.1f} s old, was {loaded.payload['state']}")
    return StartDecision("warm", reason + (f" (skipped {skipped})" if skipped else ""), loaded)


# -- the writer thread ----------------------------------------------------------------------

class RetainWriter:
    """One background thread writes snapshots, so fsync never stalls a scan. The scan hands
    over a Capture; if the previous one is still being written, the newer replaces the
    pending one (a single writer, newest wins)."""

    def __init__(self, store: RetainStore) -> None:
        self.store = store
        self._cond = threading.Condition()
        self._pending: Capture | None = None
        self._closing = False
        self.writes = 0
        self.errors = 0
        self.last_error = ""
        self.last_write_us = 0
        self.max_write_us = 0
        self.last_path = ""
        self._thread = threading.Thread(target=self._run, name="retain-writer", daemon=True)
        self._thread.start()

    def submit(self, cap: Capture) -> None:
        with self._cond:
            self._pending = cap
            self._cond.notify()

    def close(self, timeout_s: float = 10.0) -> None:
        """Write what is pending, then stop the thread and release the state directory."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)
        self.store.close()

    def _run(self) -> None:
        background_thread()
        while True:
            with self._cond:
                while self._pending is None and not self._closing:
                    self._cond.wait()
                cap, self._pending = self._pending, None
                if cap is None:
                    return
            self._write(cap)

    def _write(self, cap: Capture) -> None:
        began = time.perf_counter_ns()
        try:
            path = self.store.write(encode(cap, self.store.seq + 1, time.time_ns()))
        except OSError as exc:  # a full disk must not stop the PLC: status shows it
            self.errors += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            return
        self.last_write_us = (time.perf_counter_ns() - began) // 1000
        self.max_write_us = max(self.max_write_us, self.last_write_us)
        self.writes += 1
        self.last_path = path.name

    def info(self) -> dict[str, Any]:
        return {"dir": str(self.store.directory), "writes": self.writes, "last": self.last_path,
                "last_write_us": self.last_write_us, "max_write_us": self.max_write_us,
                "errors": self.errors, "last_error": self.last_error}
