"""Private files written whole: users, keys, certificates, the signers of programs.

Owns: `write_private(path, data)`: the bytes go to a 0600 file beside `path` (mkstemp),
flushed to the disk, then renamed over it, so a reader sees the old file or the whole new one
and a crash leaves no half-written key; the directory is synced when asked (the users file:
a change that must survive a power loss).
Does not know: what the files hold.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def write_private(path: Path, data: bytes, sync_directory: bool = False) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")  # 0600
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    if sync_directory:
        directory = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
