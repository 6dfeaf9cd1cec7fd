"""Test helpers: a SnapshotSource over a real ProcessImage, raw Modbus TCP frames, and a real
ModbusSlave served by its own asyncio loop in a thread (SlaveThread, run_in_thread)."""

from __future__ import annotations

import asyncio
import socket
import struct
import threading
from dataclasses import replace
from typing import Any

from softplc.core.image import ImageSizes, ProcessImage
from softplc.core.snapshot import HmiWrite, Snapshot, Status
from softplc.hmi.server import ModbusSlave


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
            for write in self.writes:  # as the scan applies them (core/plc.py apply_hmi)
                self.image.write_registers(write.address, write.values)
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


class SlaveThread:
    """A ModbusSlave served by its own asyncio loop in a daemon thread."""

    def __init__(self, slave: ModbusSlave, start_timeout_s: float = 5.0) -> None:
        self.slave = slave
        self._ready = threading.Event()
        self._failure: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._thread = threading.Thread(target=asyncio.run, args=(self._main(),), daemon=True)
        self._thread.name = "modbus-slave"
        self._thread.start()
        if not self._ready.wait(start_timeout_s):
            raise TimeoutError(f"Modbus slave did not start within {start_timeout_s} s")
        if self._failure is not None:
            self._thread.join()
            raise self._failure

    @property
    def port(self) -> int:
        return self.slave.bound_port

    def stop(self, timeout_s: float = 5.0) -> None:
        loop, stop_event = self._loop, self._stop_event
        if loop is not None and stop_event is not None and self._thread.is_alive():
            loop.call_soon_threadsafe(stop_event.set)
        self._thread.join(timeout_s)

    def __enter__(self) -> SlaveThread:
        return self

    def __exit__(self, *exc_info: Any) -> None:
        self.stop()

    async def _main(self) -> None:
        try:
            await self.slave.start()
        except BaseException as exc:
            self._failure = exc
            self._ready.set()
            return
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        self._ready.set()
        try:
            await self._stop_event.wait()
        finally:
            await self.slave.stop()


def run_in_thread(slave: ModbusSlave, start_timeout_s: float = 5.0) -> SlaveThread:
    """Start `slave` in a thread; returns once it listens (`.port`), stop with `.stop()`."""
    return SlaveThread(slave, start_timeout_s)
