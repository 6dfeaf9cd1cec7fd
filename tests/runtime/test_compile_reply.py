"""A big reply of the compile process goes through a file in /dev/shm, read in one call and
removed (runtime/compileproc.py _packed; issue 40 item 8); a small one stays in the pipe."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import pytest

from softplc.runtime.compileproc import BY_FILE_BYTES, _packed, _unpacked


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="no /dev/shm")
def test_a_big_reply_goes_through_a_file_that_is_removed_once_read() -> None:
    value = tuple(bytes([k]) * 4096 for k in range(64))  # 256 KiB in pieces, as wire.dumps
    message = _packed(pickle.dumps(("ok", value), protocol=5))
    assert len(message) < 1024  # the file's name, not the reply
    kind, path = pickle.loads(message)
    assert kind == "file" and Path(path).name.startswith(f"softplc_{os.getpid()}_reply_")
    assert os.stat(path).st_mode & 0o077 == 0  # this user's only
    assert _unpacked(message) == ("ok", value)
    assert not Path(path).exists()


def test_a_small_reply_stays_in_the_pipe() -> None:
    data = pickle.dumps(("error", "x" * 100), protocol=5)
    assert len(data) <= BY_FILE_BYTES and _packed(data) == data
    assert _unpacked(data) == ("error", "x" * 100)
