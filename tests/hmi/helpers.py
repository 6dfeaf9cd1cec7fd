"""Test helpers: a SnapshotSource over a real ProcessImage, and raw Modbus TCP frames."""

from __future__ import annotations

import socket
import struct
import threading
from dataclasses import replace

from softplc.core.image import ImageSizes, ProcessImage
from softplc.core.snapshot import HmiWrite, Snapshot, Status


class ImageSource:
    """The SnapshotSource contract over a ProcessImage the test fills in. `publish()` plays
    the scan: it applies the journaled writes and bumps the sequence number."""

    def __init__(self, sizes: ImageSizes | None = None, status: Status | None = None) -> None:
        self.image = ProcessImage(sizes)
        self.status = status or Status()
        self.writes: list[HmiWrite] = []
        self._seq = 0
        self._lock = threading.Lock()
        self._snapshot = self._take()

    def _take(self) -> Snapshot:
        return Snapshot(self._seq, self.image.copy(), self.status)

    def latest(self) -> Snapshot:
        with self._lock:
            return self._snapshot

    def sink(self, write: HmiWrite) -> None:
        with self._lock:
            self.writes.append(write)

    def publish(self) -> None:
        with self._lock:
            for write in self.writes:
                a = write.address
                for i, v in enumerate(write.values):
                    self.image.set(replace(a, index=a.index + i), v)
            self.writes.clear()
            self._seq += 1
            self.status = replace(self.status, scan_count=self._seq)
            self._snapshot = self._take()


def adu(pdu: bytes, tid: int = 1, unit: int = 1, pid: int = 0) -> bytes:
    return struct.pack(">HHHB", tid, pid, len(pdu) + 1, unit) + pdu


def recv_adu(sock: socket.socket) -> tuple[int, int, int, bytes]:
    """(tid, pid, unit, pdu) of the next reply; raises on EOF or socket timeout."""
    header = recv_exact(sock, 7)
    tid, pid, length, unit = struct.unpack(">HHHB", header)
    return tid, pid, unit, recv_exact(sock, length - 1)


def recv_exact(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError(f"EOF after {len(data)} of {n} bytes")
        data += chunk
    return data


def request(sock: socket.socket, pdu: bytes, tid: int = 1, unit: int = 1) -> bytes:
    """Send one request, check the MBAP echo, return the response PDU."""
    sock.sendall(adu(pdu, tid, unit))
    r_tid, r_pid, r_unit, r_pdu = recv_adu(sock)
    assert (r_tid, r_pid, r_unit) == (tid, 0, unit)
    return r_pdu


def connect(port: int, timeout_s: float = 3.0) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout_s)
    sock.settimeout(timeout_s)
    return sock


def is_closed_by_peer(sock: socket.socket) -> bool:
    """True when the peer closed the connection (EOF or reset) before the socket timeout."""
    try:
        return sock.recv(1) == b""
    except ConnectionResetError:
        return True
