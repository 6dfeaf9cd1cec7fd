"""A line per compile, for tests that count them: `softplc run` compiles its start program once,
in a compile process, never in the scan process (docs/design.md section 12).

Owns: SOFTPLC_COMPILE_LOG (a file path; unset: nothing is written): each compile of a program
text appends "<pid> <process name> <file>". Does not know: what compiling means.
"""

from __future__ import annotations

import os


def note(filename: str) -> None:
    """Log a compile of `filename` when SOFTPLC_COMPILE_LOG names a file."""
    log = os.environ.get("SOFTPLC_COMPILE_LOG")
    if not log:
        return
    try:
        with open("/proc/self/comm", encoding="utf-8") as comm:
            name = comm.read().strip()
    except OSError:
        name = "?"
    with open(log, "a", encoding="utf-8") as out:  # one short write: lines do not interleave
        out.write(f"{os.getpid()} {name} {filename}\n")
