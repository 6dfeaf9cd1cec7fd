"""Retain and warm restart: the PLC's state in files that survive a crash or a power loss.

Owns: the start decision (cold or warm, and why), the continued scan clock, and the writer
thread, which cannot die: any failure (a full disk, a value that is not JSON, a bug) is
counted by stage in `info()` and the next capture is tried at the next interval; a clean stop
writes its final snapshot synchronously and says whether it did (`RetainWriter.stop`).
What is retained, capturing, encoding and restoring it are runtime/retain/codec.py; the files
themselves (format, checked write, read-back, keeping two valid snapshots, the lock) are
runtime/retain/store.py; the names of both are re-exported here.
Does not know: scan timing, Modbus, HTTP, other processes than the one holding the lock.

Time across a restart: every timer (enabling delays, three-phase firings, the stop instant)
is kept in scan-clock nanoseconds, and a warm restart continues the scan clock from the
snapshot's scan time (ContinuedClock). Elapsed time is preserved and the downtime does not
count, exactly as when the PLC is stopped and resumed: a 2 s delay with 0.5 s left at the
snapshot has 0.5 s left after the restart. What ran between the last snapshot and the
crash (at most one retain interval) is lost and runs again.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

from softplc.core.net import CompiledNet
from softplc.runtime.clock import Clock
from softplc.runtime.realtime import background_thread
from softplc.runtime.retain.codec import (
    Capture,
    RetainValueError,
    capture,
    encode,
    load_plant,
    restore,
    restore_persistent,
)
from softplc.runtime.retain.store import (
    FORMAT,
    KEEP,
    LOCK_FILE,
    PREFIX,
    SUFFIX,
    FileOps,
    Loaded,
    RetainStore,
    SnapshotInvalid,
    Stage,
    StateDirBusy,
    WriteFailed,
    check_state_dir,
    from_bytes,
    lock_state_dir,
    secure_state_dir,
    to_bytes,
)

__all__ = ["FORMAT", "KEEP", "LOCK_FILE", "PREFIX", "SUFFIX", "Capture", "ContinuedClock",
           "FileOps", "FinalWrite", "Loaded", "RetainStore", "RetainValueError", "RetainWriter",
           "SnapshotInvalid", "Stage", "StartDecision", "StateDirBusy", "WriteFailed", "capture",
           "check_state_dir", "decide", "encode", "from_bytes", "load_plant", "lock_state_dir",
           "restore", "restore_persistent", "secure_state_dir", "to_bytes"]


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


# -- the decision at start ------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class StartDecision:
    mode: str  # "cold" or "warm"
    reason: str
    snapshot: Loaded | None = None  # warm: the snapshot to restore
    ran_before: bool = False  # the state directory held a snapshot, usable or not
    persistent: Loaded | None = None  # cold: a snapshot of a program of the same name


def decide(store: RetainStore, net: CompiledNet | None, policy: str = "warm") -> StartDecision:
    """Cold or warm, and why. `policy` "cold" (the boot policy, docs/retain.md) does not
    restore a snapshot of the same program; persistent values come back at any cold start
    from a snapshot of a program of the same name."""
    loaded, problems = store.load_newest()
    skipped = "; ".join(problems)
    if net is None:
        return StartDecision("cold", "no program on the command line", ran_before=bool(problems))
    if loaded is None:
        return StartDecision("cold", skipped or f"no snapshot in {store.directory}",
                             ran_before=bool(problems))
    same_name = loaded if loaded.payload.get("program") == net.name else None
    snap_hash = loaded.payload["program_hash"]
    if snap_hash != net.program_hash:
        return StartDecision("cold", f"snapshot {loaded.path.name} program "
                             f"{loaded.payload.get('program')} hash {snap_hash[:12]} differs "
                             f"from program {net.name} hash {net.program_hash[:12]}",
                             ran_before=True, persistent=same_name)
    if policy == "cold":
        return StartDecision("cold", f"boot policy cold: snapshot {loaded.path.name} not "
                             f"restored (was {loaded.payload['state']})", ran_before=True,
                             persistent=loaded)
    # Wall-clock age, for a person to read; the scan clock continues regardless.
    age_s = (time.time_ns() - int(loaded.payload.get("written_unix_ns", 0))) / 1e9
    reason = (f"snapshot {loaded.path.name} from scan {loaded.payload['scan_count']}, "
              f"{age_s:.1f} s old, was {loaded.payload['state']}")
    return StartDecision("warm", reason + (f" (skipped {skipped})" if skipped else ""), loaded,
                         ran_before=True)


# -- the writer thread ----------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class FinalWrite:
    """What became of the snapshot of a clean stop: the shutdown says it, status shows it."""

    written: bool
    path: str = ""
    error: str = ""

    def __str__(self) -> str:
        if self.written:
            return f"final snapshot {self.path} written"
        return f"final snapshot NOT written: {self.error}"


class RetainWriter:
    """One background thread writes snapshots, so fsync never stalls a scan. The scan hands
    over a Capture; if the previous one is still being written, the newer replaces the
    pending one (a single writer, newest wins). The thread cannot die: every failure is
    counted by stage and the next capture is written at the next interval."""

    def __init__(self, store: RetainStore) -> None:
        self.store = store
        self._cond = threading.Condition()
        self._pending: Capture | None = None
        self._closing = False
        self.writes = 0
        self.errors = 0
        self.errors_by_stage: dict[str, int] = {stage.value: 0 for stage in Stage}
        self.consecutive_errors = 0
        self.last_error = ""
        self.last_write_us = 0
        self.max_write_us = 0
        self.last_path = ""
        self.restarts = 0
        self.final: FinalWrite | None = None
        self._last = FinalWrite(False, "", "nothing written yet")
        self._held: Capture | None = None  # submit(later=True), until settle()
        self._thread = self._start()

    def _start(self) -> threading.Thread:
        thread = threading.Thread(target=self._run, name="retain-writer", daemon=True)
        thread.start()
        return thread

    def submit(self, cap: Capture, later: bool = False) -> None:
        """`cap` to write next (replacing one not yet taken). `later`: held until settle(),
        after the scan (woken in the scan, the writer took the interpreter lock from it to
        encode: every capture's scan ran ~1.3 ms at a 1 ms period, a slot a second)."""
        if later:
            self._held = cap
            return
        with self._cond:
            if self._closing:
                return
            self._pending = cap
            self._cond.notify()
        if not self._thread.is_alive():  # only a BaseException could end it: start anew
            self.restarts += 1
            self._failed(Stage.OTHER, "writer thread had ended; restarted")
            self._thread = self._start()

    def settle(self) -> None:
        """The capture held by submit(later=True), to the writer thread."""
        if (cap := self._held) is not None:
            self._held = None
            self.submit(cap)

    def stop(self, cap: Capture | None, timeout_s: float = 10.0) -> FinalWrite:
        """At a clean stop: wait (bounded) for a write in progress, drop what is pending (`cap`
        is newer), write `cap` synchronously in the caller's thread, release the state
        directory. Returns whether the final snapshot is on disk, and why not."""
        with self._cond:
            self._closing = True
            self._pending = None
            self._cond.notify()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            result = FinalWrite(False, "", f"the writer was still busy after {timeout_s:g} s")
        elif cap is None:
            result = FinalWrite(False, "", "no program to retain")
        else:
            result = self._write(cap)
        return self._finish(result)

    def close(self, timeout_s: float = 10.0) -> FinalWrite:
        """Write what is pending (synchronously), then stop the thread and release the state
        directory. Returns the fate of the last capture submitted."""
        with self._cond:
            cap, self._pending = self._held or self._pending, None  # the newest
        self._held = None
        if cap is not None:
            return self.stop(cap, timeout_s)
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            return self._finish(FinalWrite(False, "", f"the writer was still busy after "
                                                      f"{timeout_s:g} s"))
        return self._finish(self._last)

    def _finish(self, result: FinalWrite) -> FinalWrite:
        self.final = result
        self.store.close()
        return result

    def _run(self) -> None:
        try:
            background_thread()
        except Exception as exc:  # scheduling is a preference; writing is the job
            self._failed(Stage.OTHER, f"background scheduling: {type(exc).__name__}: {exc}")
        while True:
            with self._cond:
                while self._pending is None and not self._closing:
                    self._cond.wait()
                cap, self._pending = self._pending, None
                if cap is None:
                    return
            self._write(cap)

    def _write(self, cap: Capture) -> FinalWrite:
        """Encode and write one capture. Never raises: a failure is counted and returned."""
        began = time.perf_counter_ns()
        try:
            path = self.store.write(encode(cap, self.store.seq + 1, time.time_ns()))
        except WriteFailed as exc:  # a full disk must not stop the PLC: status shows it
            return self._failed(exc.stage, str(exc))
        except (RetainValueError, TypeError, ValueError) as exc:
            return self._failed(Stage.ENCODE, f"{type(exc).__name__}: {exc}")
        except Exception as exc:  # a bug must not end retain for good either
            return self._failed(Stage.OTHER, f"{type(exc).__name__}: {exc}")
        self.last_write_us = (time.perf_counter_ns() - began) // 1000
        self.max_write_us = max(self.max_write_us, self.last_write_us)
        self.writes += 1
        self.consecutive_errors = 0
        self.last_path = path.name
        self._last = FinalWrite(True, path.name)
        return self._last

    def _failed(self, stage: Stage, message: str) -> FinalWrite:
        self.errors += 1
        self.errors_by_stage[stage.value] += 1
        self.consecutive_errors += 1
        self.last_error = message if message.startswith(stage.value) else \
            f"{stage.value}: {message}"
        self._last = FinalWrite(False, "", self.last_error)
        return self._last

    def info(self) -> dict[str, Any]:
        final = self.final
        return {"dir": str(self.store.directory), "dir_note": self.store.dir_note,
                "writes": self.writes, "last": self.last_path,
                "last_write_us": self.last_write_us, "max_write_us": self.max_write_us,
                "errors": self.errors, "last_error": self.last_error,
                "errors_by_stage": dict(self.errors_by_stage),
                "consecutive_errors": self.consecutive_errors,
                "temps_removed": self.store.temps_removed,
                "cleanup_errors": self.store.cleanup_errors, "restarts": self.restarts,
                "final": None if final is None else {"written": final.written,
                                                     "path": final.path, "error": final.error}}
