"""Helpers every child process of `softplc run` uses.

Owns: ending a child when its supervisor ends (PR_SET_PDEATHSIG), each process's name in
process lists (PR_SET_NAME), the stop signal and the words a child says to the supervisor
("ready", "safe"; safe against a child killed at any moment), ending a child at once when
its work is done (exit_now), and finding a process's children.
Does not know: what the child does.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.context import BaseContext
from pathlib import Path
from typing import Final, NoReturn, Protocol

log = logging.getLogger(__name__)
PR_SET_NAME: Final = 15  # <linux/prctl.h>
COMM_BYTES: Final = 15  # Linux's comm: 16 bytes with the final NUL


def die_with_parent() -> None:
    """In a child process: end when the supervisor ends, even if it was killed (SIGKILL).
    Linux delivers SIGTERM on the parent's death (PR_SET_PDEATHSIG); the loops also poll."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def name_process(name: str | None = None) -> None:
    """Show this process as `name` (at most COMM_BYTES; default: the name it was started
    under, multiprocessing's Process(name=), which names it for Python only) in `ps -o comm`,
    `top` and /proc/PID/comm, where every softplc process showed as `python`. A process that
    cannot be named works the same: logged at debug level, never an error."""
    if name is None:
        import multiprocessing

        name = multiprocessing.current_process().name
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:COMM_BYTES]), 0, 0, 0):
            raise OSError(ctypes.get_errno(), os.strerror(ctypes.get_errno()))
    except (OSError, AttributeError) as exc:  # not Linux, no libc, refused
        log.debug("process name %r not set: %s", name, exc)


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
        self.tell()

    def tell(self) -> None:
        """Parent side: SIGTERM to the bound child, nothing else. Takes no lock, so a signal
        handler may call it (set() may not: the handler can interrupt the thread that holds
        the event's lock, and wait on it for ever)."""
        for pid in self._pids:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGTERM)

    def is_set(self) -> bool:
        return self._event.is_set()

    def wait(self, timeout: float | None = None) -> bool:
        return self._event.wait(timeout)


class ReadySignal:
    """A child says once that it is ready; the parent waits for it with a timeout. The scan
    process says a second word, "safe", once the devices confirmed its safe outputs at a stop:
    the supervisor stops the service processes only then. A pipe, so that a child killed
    at any moment leaves nothing locked behind (see StopFlag)."""

    READY, SAFE = b"ready", b"safe"

    def __init__(self, ctx: BaseContext) -> None:
        self._reader, self._writer = ctx.Pipe(duplex=False)

    def set(self) -> None:
        """Child side: ready."""
        self.say(self.READY)

    def say(self, word: bytes) -> None:
        """Child side."""
        with contextlib.suppress(OSError):
            self._writer.send_bytes(word)

    def wait(self, timeout: float | None = None) -> bool:
        """Parent side: True once the child said it is ready (its first word)."""
        try:
            return bool(self._reader.poll(timeout))
        except (OSError, EOFError):
            return False

    def heard(self, word: bytes, timeout: float) -> bool:
        """Parent side: True once the child said `word`; the words before it are read and
        dropped. False after `timeout` (the parent keeps a writer open: no EOF comes when the
        child dies, so the caller watches the child itself)."""
        deadline = time.monotonic() + timeout
        try:
            while self._reader.poll(max(0.0, deadline - time.monotonic())):
                if self._reader.recv_bytes() == word:
                    return True
        except (OSError, EOFError):
            pass
        return False


def exit_now(code: int = 0) -> NoReturn:
    """End this child process at once, without the interpreter's teardown: freeing a large
    heap object by object (asyncua's address space) took 0.8-2.4 s on the loaded 2-core
    machine, past the supervisor's 2 s. Only once everything that must be written is (the
    services closed, the outputs safe and confirmed, the final retain snapshot)."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)


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
