"""The status board: a JSON document the scan process publishes for the API, in shared memory.

Owns: a fixed-size shared-memory segment holding one JSON document (program name, marking by
place, timing summary, drivers' health, recent events with sequence numbers), written with a
sequence lock so a reader never sees half of one document and half of the next.
Does not know: what the document means to HTTP clients.

The process image and the Modbus status block go through shm.py every scan; this board is
richer and slower (JSON), so the scan loop refreshes it every few scans only.
"""

from __future__ import annotations

import contextlib
import json
import struct
from multiprocessing import shared_memory
from typing import Any

BOARD_BYTES = 1 << 20
_HEADER = struct.Struct("<QQ")  # sequence (odd while writing), payload length


class StatusBoard:
    def __init__(self, shm: shared_memory.SharedMemory, owner: bool) -> None:
        self._shm = shm
        self._owner = owner
        self._seq = 0

    @classmethod
    def create(cls, name: str) -> StatusBoard:
        try:
            stale = shared_memory.SharedMemory(name=name)
            stale.close()
            stale.unlink()  # left over by a killed run: never block a restart
        except FileNotFoundError:
            pass
        board = cls(shared_memory.SharedMemory(name=name, create=True, size=BOARD_BYTES), True)
        board.publish({})
        return board

    @classmethod
    def open_or_create(cls, name: str) -> tuple[StatusBoard, bool]:
        """Publish into board `name` if a supervisor created it, else create it; returns the
        board and whether this call created it."""
        try:
            board = cls(shared_memory.SharedMemory(name=name), False)
        except FileNotFoundError:
            return cls.create(name), True
        buf = board._shm.buf
        assert buf is not None
        board._seq = _HEADER.unpack_from(buf, 0)[0] // 2 + 1
        return board, False

    @classmethod
    def attach(cls, name: str) -> StatusBoard:
        # Readers are children of the same supervisor and share its resource tracker, so
        # the registration Python 3.11 makes on attach is the owner's one: leave it alone.
        return cls(shared_memory.SharedMemory(name=name), False)

    def publish(self, document: dict[str, Any]) -> None:
        payload = json.dumps(document, separators=(",", ":")).encode()
        limit = BOARD_BYTES - _HEADER.size
        if len(payload) > limit:
            payload = json.dumps({"error": "status document too large", **{
                k: v for k, v in document.items() if k in ("state", "program", "scan_count")
            }}).encode()
        buf = self._shm.buf
        assert buf is not None
        self._seq += 1
        _HEADER.pack_into(buf, 0, self._seq * 2 - 1, 0)
        buf[_HEADER.size:_HEADER.size + len(payload)] = payload
        _HEADER.pack_into(buf, 0, self._seq * 2, len(payload))

    def read(self, attempts: int = 1000) -> dict[str, Any]:
        buf = self._shm.buf
        assert buf is not None
        for _ in range(attempts):
            seq, length = _HEADER.unpack_from(buf, 0)
            if seq % 2:
                continue
            payload = bytes(buf[_HEADER.size:_HEADER.size + length])
            if _HEADER.unpack_from(buf, 0)[0] == seq:
                result: dict[str, Any] = json.loads(payload) if payload else {}
                return result
        raise TimeoutError("status board is being rewritten continuously")

    def detach(self) -> None:
        """Unmap without removing: the segment belongs to whoever created it."""
        self._shm.close()

    def close(self) -> None:
        self._shm.close()
        if self._owner:
            with contextlib.suppress(FileNotFoundError):
                self._shm.unlink()
