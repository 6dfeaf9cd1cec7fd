"""Closed-loop clients for the runtime benchmarks, in a process of their own so that their
CPU is never counted as the server's: Modbus TCP pollers (FC3, raw sockets: the cheapest
client Python has, so the server, not the client, sets the pace) and an HTTP status poller.

Owns: LoadJob (what to run), the client threads, LoadWorker (the client process, reused
across jobs to pay its start-up once).
Does not know: which server answers (ours or plain pymodbus), scans, what the figures mean.
"""

from __future__ import annotations

import contextlib
import http.client
import multiprocessing as mp
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any
from urllib.parse import urlsplit

from softplc.bench.measure import figures
from softplc.runtime.realtime import Realtime, keep_off_scan_cpu

_CTX = mp.get_context("spawn")
_REQUEST = struct.Struct(">HHHBBHH")  # MBAP (transaction, protocol 0, length 6, unit) + PDU
_WARMUP_REQUESTS = 5


@dataclass(frozen=True, slots=True)
class LoadJob:
    """`clients` Modbus connections each reading `registers` holding registers from address 0
    in a closed loop, and, if `api_url`, GET /api/v1/status every `http_interval_s`."""

    modbus_port: int | None
    clients: int
    duration_s: float
    api_url: str | None = None
    http_interval_s: float = 0.01
    registers: int = 100
    keep_latencies: bool = False  # return every Modbus latency (µs) to pool rounds


@dataclass(slots=True)
class _Tally:
    latencies_us: list[float]
    errors: int = 0
    first_error: str = ""

    def fail(self, exc: BaseException | str) -> None:
        self.errors += 1
        self.first_error = self.first_error or str(exc)


def client_process(target: Callable[..., None], args: tuple[Any, ...], name: str,
                   realtime: Realtime, timeout_s: float, what: str) -> dict[str, Any]:
    """Run `target(*args, results)` in a client process off the scan's CPU and return the
    dict it sends on `results`; RuntimeError naming `what` if nothing comes in `timeout_s`."""
    here, there = _CTX.Pipe(duplex=False)
    proc = _CTX.Process(target=target, args=(*args, there), name=name, daemon=True)
    proc.start()
    keep_off_scan_cpu(int(proc.pid or 0), realtime)
    try:
        if not here.poll(timeout_s):
            raise RuntimeError(f"{what} did not report")
        result: dict[str, Any] = here.recv()
    finally:
        proc.join(10)
        if proc.is_alive():
            proc.kill()
    return result


def _read_reply(sock: socket.socket) -> bytes:
    data = sock.recv(4096)
    while len(data) < 6 or len(data) < 6 + int.from_bytes(data[4:6], "big"):
        more = sock.recv(4096)
        if not more:
            raise ConnectionError("the server closed the connection")
        data += more
    return data


def _modbus_client(port: int, registers: int, barrier: threading.Barrier, duration_s: float,
                   tally: _Tally) -> None:
    expected = 9 + 2 * registers
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            for tid in range(_WARMUP_REQUESTS):
                sock.sendall(_REQUEST.pack(tid, 0, 6, 1, 3, 0, registers))
                _read_reply(sock)
            barrier.wait(30)
            deadline_ns = time.monotonic_ns() + int(duration_s * 1e9)
            tid = 0
            while True:
                began = time.monotonic_ns()
                if began >= deadline_ns:
                    break
                tid = (tid + 1) & 0xFFFF
                sock.sendall(_REQUEST.pack(tid, 0, 6, 1, 3, 0, registers))
                reply = _read_reply(sock)
                tally.latencies_us.append((time.monotonic_ns() - began) / 1000)
                answered = int.from_bytes(reply[:2], "big")
                if len(reply) != expected or reply[7] != 3 or answered != tid:
                    tally.fail(f"unexpected reply {reply[:12].hex()}")
    except (OSError, threading.BrokenBarrierError) as exc:
        tally.fail(exc)
        barrier.abort()


def _http_client(url: str, interval_s: float, barrier: threading.Barrier, duration_s: float,
                 tally: _Tally) -> None:
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname or "127.0.0.1", parts.port, timeout=10)
    try:
        barrier.wait(30)
        deadline_ns = time.monotonic_ns() + int(duration_s * 1e9)
        while (began := time.monotonic_ns()) < deadline_ns:
            conn.request("GET", "/api/v1/status")
            response = conn.getresponse()
            response.read()
            tally.latencies_us.append((time.monotonic_ns() - began) / 1000)
            if response.status != 200:
                tally.fail(f"HTTP {response.status}")
            time.sleep(interval_s)
    except (OSError, http.client.HTTPException, threading.BrokenBarrierError) as exc:
        tally.fail(exc)
        barrier.abort()
    finally:
        conn.close()


def run_job(job: LoadJob) -> dict[str, Any]:
    """Run `job` in this process; requests, rates and latency figures (µs)."""
    modbus = [_Tally([]) for _ in range(job.clients if job.modbus_port else 0)]
    web = _Tally([]) if job.api_url else None
    barrier = threading.Barrier(len(modbus) + (web is not None) + 1)
    threads = [threading.Thread(target=_modbus_client, daemon=True, args=(
        job.modbus_port, job.registers, barrier, job.duration_s, t)) for t in modbus]
    if web is not None and job.api_url:
        threads.append(threading.Thread(target=_http_client, daemon=True, args=(
            job.api_url, job.http_interval_s, barrier, job.duration_s, web)))
    for thread in threads:
        thread.start()
    with contextlib.suppress(threading.BrokenBarrierError):
        barrier.wait(60)
    t0_ns = time.monotonic_ns()  # monotonic is system-wide: the scan record uses it too
    for thread in threads:
        thread.join(job.duration_s + 30)
    t1_ns = time.monotonic_ns()
    elapsed_s = max((t1_ns - t0_ns) / 1e9, 1e-9)
    latencies = [x for t in modbus for x in t.latencies_us]
    result: dict[str, Any] = {
        "clients": len(modbus), "registers": job.registers, "duration_s": elapsed_s,
        "t0_ns": t0_ns, "t1_ns": t1_ns,
        "requests": len(latencies), "requests_per_s": len(latencies) / elapsed_s,
        "errors": sum(t.errors for t in modbus),
        "first_error": next((t.first_error for t in modbus if t.first_error), ""),
        "per_client": [len(t.latencies_us) for t in modbus],
        "latency_us": figures(latencies).as_dict(),
    }
    if job.keep_latencies:
        result["latencies_us"] = latencies
    if web is not None:
        result["http"] = {"requests": len(web.latencies_us), "errors": web.errors,
                          "first_error": web.first_error, "interval_s": job.http_interval_s,
                          "latency_us": figures(web.latencies_us).as_dict()}
    return result


def _worker_main(jobs: Connection) -> None:
    from softplc.runtime.shared.procs import die_with_parent

    die_with_parent()
    while True:
        job = jobs.recv()
        if job is None:
            return
        jobs.send(run_job(job))


class LoadWorker:
    """The client process. submit() a job, then result(); close() ends the process."""

    def __init__(self) -> None:
        self._conn, child = _CTX.Pipe(duplex=True)
        self._proc = _CTX.Process(target=_worker_main, args=(child,), name="softplc-bench-load",
                                  daemon=True)
        self._proc.start()
        self._busy: LoadJob | None = None

    @property
    def pid(self) -> int:
        return int(self._proc.pid or 0)

    def submit(self, job: LoadJob) -> None:
        if self._busy is not None:
            raise RuntimeError("the load worker is already running a job")
        self._conn.send(job)
        self._busy = job

    def result(self) -> dict[str, Any]:
        job = self._busy
        if job is None:
            raise RuntimeError("no job was submitted")
        if not self._conn.poll(job.duration_s + 120):
            raise RuntimeError("the load worker did not report")
        self._busy = None
        answer: dict[str, Any] = self._conn.recv()
        return answer

    def run(self, job: LoadJob) -> dict[str, Any]:
        self.submit(job)
        return self.result()

    def close(self) -> None:
        if self._proc.is_alive():
            with contextlib.suppress(OSError):
                self._conn.send(None)
            self._proc.join(10 + (self._busy.duration_s if self._busy else 0))
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5)
        self._conn.close()

    def __enter__(self) -> LoadWorker:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
