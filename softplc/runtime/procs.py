"""Helpers every child process of `softplc run` uses.

Owns: ending a child when its supervisor ends (PR_SET_PDEATHSIG). Does not know: what the
child does.
"""

from __future__ import annotations

import signal


def die_with_parent() -> None:
    """In a child process: end when the supervisor ends, even if it was killed (SIGKILL).
    Linux delivers SIGTERM on the parent's death (PR_SET_PDEATHSIG); the loops also poll."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
