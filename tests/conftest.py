"""Session-wide: pytest exits as soon as it has printed its summary, and no test or import
changes how the process takes a closed pipe.

Owns: the test process's open descriptors stay well below select()'s 1024; SIGPIPE stays
ignored (Python's setting): a test or a library import that sets its
default action (vcdvcd's import did) made the next write to a closed socket, in any later
test, kill pytest with no report; the test after which it changed fails, naming it. And the
end of the session. What a test left running (a non-daemon thread, a thread-pool
worker blocked in a call, a multiprocessing child) may not keep the interpreter alive after
the summary: children are terminated, threads get GRACE_S to end, then the process exits
with pytest's own status, naming on stderr what it left behind so that the test that
leaked it can be found.
Does not know: any test's subject.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
import time
from typing import Final

import pytest

GRACE_S: Final = 2.0
_exit_status: list[int] = [0]


# select() (pymodbus's sync client uses it) fails on a descriptor >= 1024: the test process
# must never hold that many. Leaks (a Channel's 12 pipe ends per API test, never closed) once
# took it there two thirds of the way through the suite.
MAX_OPEN_FDS: Final = 768


@pytest.fixture(autouse=True)
def _descriptors_do_not_leak() -> object:
    yield
    count = len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else 0
    if count > MAX_OPEN_FDS:
        pytest.fail(f"the test process holds {count} open descriptors (at most "
                    f"{MAX_OPEN_FDS}): a test before this one leaks them (select() fails "
                    "at 1024)")


@pytest.fixture(autouse=True)
def _sigpipe_stays_ignored() -> object:
    """Checked before each test (an import while collecting) and after it."""
    for when in ("before", "after"):
        found = signal.getsignal(signal.SIGPIPE)
        if found != signal.SIG_IGN:
            signal.signal(signal.SIGPIPE, signal.SIG_IGN)  # the next tests run as they should
            pytest.fail(f"SIGPIPE's handler is {found!r} {when} this test (set by it, or by an "
                        "import while collecting), not ignored: a write to a closed socket "
                        "would kill pytest")
        if when == "before":
            yield


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    _exit_status[0] = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config: pytest.Config) -> None:
    """After the summary: end what tests left running, or leave without waiting for it."""
    children = multiprocessing.active_children()
    for child in children:
        child.terminate()
    for child in children:
        child.join(1.0)
        if child.is_alive():
            child.kill()
            child.join(1.0)
    deadline = time.monotonic() + GRACE_S
    left = [t for t in threading.enumerate()
            if t is not threading.main_thread() and not t.daemon and t.is_alive()]
    for thread in left:
        thread.join(max(deadline - time.monotonic(), 0.0))
    left = [t for t in left if t.is_alive()]
    if children or left:
        names = ", ".join([f"process {c.name}" for c in children] +
                          [f"thread {t.name}" for t in left])
        sys.stderr.write(f"\nleft running by the tests: {names}\n")
    if left:  # the interpreter would wait for them at exit: do not
        sys.stdout.flush()
        sys.stderr.write("exiting without waiting for them\n")
        sys.stderr.flush()
        os._exit(_exit_status[0])
