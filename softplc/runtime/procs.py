"""Helpers every child process of `softplc run` uses.

Owns: ending a child when its supervisor ends (PR_SET_PDEATHSIG), the stop and ready
signals between the supervisor and its children (safe against a child killed at any moment),
and finding a process's children.
Does not know: what the child does.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable
from multiprocessing.context import BaseContext
from pathlib import Path
from typing import Protocol


def die_with_parent() -> None:
    """In a child process: end when the supervisor ends, even if it was killed (SIGKILL).
    Linux delivers SIGTERM on the parent's death (PR_SET_PDEATHSIG); the loops also poll."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def children(pid: int) -> list[int]:
    """The live (not zombie) processes whose parent is `pid`, from /proc (Linux): the scan
    process's compile process, for the memory bench and tests."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                if int(fields[1]) == pid and fields[0] != "Z":
                    found.append(int(entry.name))
    return found


def supervisor_pid() -> int:
    """The pid of the process that started this one, as it was recorded at the start (not
    os.getppid() now: a parent killed before the child looked would leave it orphaned for
    good, its parent then being init)."""
    import multiprocessing

    parent = multiprocessing.parent_process()
    return parent.pid if parent is not None and parent.pid is not None else os.getppid()


class Flag(Protocol):
    """What a child's loop needs of a stop or ready signal (StopFlag, ReadySignal,
    threading.Event)."""

    def set(self) -> None: ...

    def is_set(self) -> bool: ...

    def wait(self, timeout: float | None = ...) -> bool: ...


class StopFlag:
    """Asks a child process to stop, and survives the death of any process involved.

    In the parent, set() sends SIGTERM to the bound child; in the child (which gets a fresh
    copy when the flag is passed to it), the SIGTERM handler calls set() and the loops poll
    is_set()/wait(). A multiprocessing Event is not used on purpose: a process killed while
    waiting on one leaves its condition expecting a wake-up acknowledgement, and the next
    set() blocks forever. Measured: after a kill -9 of the scan process the supervisor hung
    in Event.set() and so ignored SIGTERM and SIGINT."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self._pids: list[int] = []

    def bind(self, pid: int) -> None:
        """Parent side: set() signals this child from now on."""
        self._pids = [pid]

    def __getstate__(self) -> dict[str, object]:
        return {}

    def __setstate__(self, state: dict[str, object]) -> None:
        self._event = threading.Event()
        self._pids = []

    def set(self) -> None:
        self._event.set()
        for pid in self._pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGTERM)

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self._event.wait(timeout)


class ReadySignal:
    """A child says once that it is ready; the parent waits for it with a timeout. A pipe, so
    that a child killed at any moment leaves nothing locked behind (see StopFlag)."""

    def __init__(self, ctx: BaseContext) -> None:
        self._reader, self._writer = ctx.Pipe(duplex=False)

    def set(self) -> None:
        """Child side."""
        with contextlib.suppress(OSError):
            self._writer.send_bytes(b"ready")

    def wait(self, timeout: float | None = None) -> bool:
        """Parent side: True once the child said it is ready."""
        try:
            return bool(self._reader.poll(timeout))
        except (OSError, EOFError):
            return False


def once(action: Callable[[], object]) -> Callable[[int, object], None]:
    """A SIGTERM handler that acts on the first signal only. A dying supervisor can deliver
    SIGTERM more than once (PR_SET_PDEATHSIG fires as each of its threads exits), and one
    arriving inside stop.set() re-entered it and deadlocked on its lock, outputs still on."""
    done: dict[str, bool] = {}

    def handler(signum: int, frame: object) -> None:
        if not done:
            done["yes"] = True  # no call before this store: no other handler can run first
            action()

    return handler
