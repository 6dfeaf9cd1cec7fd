"""What a killed `softplc run` leaves in /dev/shm, and removing it at the next start.

Owns: SHM_PREFIX (the names of a run's shared-memory segments start with it and the
supervisor's pid), the list of a run's named semaphores written beside its segments, and
removing the segments and semaphores of runs whose pid is gone.
Does not know: what the segments hold, which processes use them.
"""

from __future__ import annotations

import contextlib
import gc
import multiprocessing.synchronize as mp_sync
from pathlib import Path
from typing import Final

from softplc.runtime.shared.channel import pid_alive

SHM_PREFIX: Final = "softplc_"


def remove_stale_segments() -> None:
    """Segments and named semaphores of runs that were killed (their pid is gone) are removed
    before we start: a kill -9 of the whole process group leaves both behind."""
    shm_dir = Path("/dev/shm")
    if not shm_dir.is_dir():
        return
    for entry in shm_dir.glob(SHM_PREFIX + "*"):
        parts = entry.name.split("_")
        if len(parts) < 2 or not parts[1].isdigit() or pid_alive(int(parts[1])):
            continue
        if entry.name.endswith("_sems"):
            for name in entry.read_text(encoding="utf-8", errors="replace").split():
                with contextlib.suppress(OSError):
                    (shm_dir / f"sem.{name.lstrip('/')}").unlink()
        entry.unlink(missing_ok=True)


def record_semaphores(tag: str) -> None:
    """List this process's named semaphores (multiprocessing's Events, locks) where the next
    start finds them if this run is killed before its resource tracker can unlink them."""
    locks = [getattr(o, "_semlock", None) for o in gc.get_objects()
             if isinstance(o, mp_sync.SemLock)]
    names = sorted({str(lock.name) for lock in locks  # no name: unlinked at creation
                    if lock is not None and getattr(lock, "name", None)})
    with contextlib.suppress(OSError):
        Path(f"/dev/shm/{tag}_sems").write_text("\n".join(names), encoding="utf-8")
