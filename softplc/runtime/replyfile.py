"""A compile process's reply on its way to the scan process: through the pipe when it is
small, through a file in /dev/shm when it is not, a compiled net's pieces left as they are.

Owns: `pack` (the compile process's side: the message to send for a reply) and `unpack` (the
scan process's download thread: the reply from a message). A reply over BY_FILE_BYTES goes
through a file: the download thread reads it in one system call, the interpreter lock
released; through the pipe it came in ~25 reads of 64 KiB, each taking the lock from the scan
again while the compile process, at nice 10, wrote the next. A Built's net pieces
(program/wire.py) follow the pickled head raw, and come back as views into the one buffer
read: unpickling them inside the reply copied 1.4 MB into 595 new objects, the lock held for
~0.6 ms at a time the download thread chose (a late scan in the online-change bench, issue 40
item 8); the views are unpickled a piece per step between scans (runtime/download.py).
The files are named as supervise/leftovers.py removes them when their process is gone.
Trust: as program/wire.py, only between the runtime's own processes.
Does not know: what a reply means, the scan, the pipe.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import pickle
import struct
import tempfile
from typing import Any, Final

from softplc.runtime.prepare import Built

BY_FILE_BYTES: Final = 64 << 10  # above a pipe's buffer: through a file
_MAGIC: Final = b"SPLCRPL1"
_HEAD: Final = struct.Struct("<8sQ")  # magic, length of the pickled head


def pack(reply: tuple[str, Any], directory: str = "/dev/shm") -> bytes:
    """The message that carries `reply` ((kind, value)): the reply itself, or the name of
    the file it was written to."""
    kind, value = reply
    pieces: tuple[bytes, ...] = ()
    if isinstance(value, Built):
        pieces, value = tuple(bytes(p) for p in value.net), dataclasses.replace(value, net=())
    head = pickle.dumps((kind, value, [len(p) for p in pieces]), protocol=5)
    if len(head) + sum(map(len, pieces)) <= BY_FILE_BYTES or not os.path.isdir(directory):
        return pickle.dumps(("inline", (kind, reply[1])), protocol=5)
    fd, path = tempfile.mkstemp(prefix=f"softplc_{os.getpid()}_reply_", dir=directory)
    with os.fdopen(fd, "wb") as out:
        out.write(_HEAD.pack(_MAGIC, len(head)))
        out.write(head)
        for piece in pieces:
            out.write(piece)
    return pickle.dumps(("file", path), protocol=5)


def unpack(message: bytes) -> tuple[str, Any]:
    """The reply (kind, value) that `pack` made `message` of; a file it names is removed."""
    how, what = pickle.loads(message)
    if how == "inline":
        kind, value = what
        return kind, value
    try:
        with open(what, "rb") as src:
            data = src.read()  # one read of its size: the lock released meanwhile
    finally:
        with contextlib.suppress(OSError):
            os.unlink(what)
    magic, head_len = _HEAD.unpack_from(data)
    if magic != _MAGIC:
        raise ValueError(f"{what}: not a compile reply")
    view = memoryview(data)
    start = _HEAD.size + head_len
    kind, value, lengths = pickle.loads(view[_HEAD.size:start])
    if lengths:
        pieces = []
        for length in lengths:
            pieces.append(view[start:start + length])
            start += length
        value = dataclasses.replace(value, net=tuple(pieces))
    return kind, value
