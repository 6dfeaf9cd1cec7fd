"""Benchmark section `isolation`: what each abuse of one door costs the other doors and the scan.

One runtime (transport at 1 ms, Modbus, HTTP and OPC UA on loopback). A Modbus poller and an
HTTP `/status` poller (load.py) run alone, then beside each abuse in turn, each abuse from a
process of its own: many idle OPC UA connections, a huge OPC UA Read, many OPC UA sessions
with monitored items, 300 HTTP event streams, JSON bombs to the symbol and force routes.
Keys, per abuse A: `modbus_p99_ratio_A`, `http_p99_ratio_A`, `scan_p99_ratio_A` (p99 under
the abuse / the same figure without abuse just before it, same run), the worst (`*_max`),
`scan_p99_over_floor_max` (the worst scan p99 of any phase / the empty loop's); per phase,
the CPU seconds each service process and the abuser used and where the clients ran. The
clients stand for other machines (placement.py): pollers and abusers on the scan's CPU,
the abusers at SCHED_IDLE, so the services' CPU holds only what the servers do; the Read
and the bombs are run again with every client on the services' CPU (`A_local`, `*_max_local`:
a process on the PLC's machine competes for its CPU as any does). The bombs carry the
owner's key: they reach the JSON checks, not a 401.
Owns: the abusers and the section's keys. Does not know: how the runtime starts (live.py),
how any server bounds itself (the abusers are plain clients).
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import logging
import multiprocessing as mp
import os
import socket
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Final

from softplc.bench import placement
from softplc.bench.live import LiveRuntime, cpu_s, run_floor
from softplc.bench.load import LoadJob, LoadWorker
from softplc.bench.measure import Progress, ratio
from softplc.bench.placement import Placement, place
from softplc.bench.scanbench import SETTLE_S, window_figures
from softplc.runtime.realtime import Realtime, recommended

_CTX = mp.get_context("spawn")
ABUSES: Final = ("opcua_idle", "opcua_huge_read", "opcua_sessions", "event_streams",
                 "json_bombs")
# Measured again with every client on the services' CPU (keys `..._local`, as before issue
# 28's placement): what a process on the PLC's own machine that burns CPU costs them, the
# pollers' own wake-ups included. Reported beside the others, not in the `*_max`.
LOCAL: Final = ("opcua_huge_read", "json_bombs")
# (phase name, abuse, clients remote): the order the phases run in.
RUNS: Final = (*((kind, kind, True) for kind in ABUSES),
               *((f"{kind}_local", kind, False) for kind in LOCAL))
# (quick, full) sizes of each abuse.
SIZES: Final = {"opcua_idle": (200, 900), "opcua_huge_read": (50_000, 200_000),
                "opcua_sessions": ((40, 20), (200, 50)), "event_streams": (300, 300),
                "json_bombs": (1, 1)}
BOMBS: Final = (b"[" * 100_000, b'{"value":' * 50_000, b'{"value": ' + b"9" * 500_000 + b"}",
                b"[" * 4_000)


class _Ignore:
    """asyncua subscription handler: the notifications are the load, not the result."""

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        pass


def _idle_sockets(port: int, count: int) -> list[socket.socket]:
    socks = []
    for _ in range(count):
        with contextlib.suppress(OSError):
            socks.append(socket.create_connection(("127.0.0.1", port), timeout=5))
    return socks


def _event_streams(port: int, count: int) -> tuple[list[socket.socket], dict[str, int]]:
    socks = _idle_sockets(port, count)
    heads: dict[str, int] = {}
    for sock in socks:
        with contextlib.suppress(OSError):
            sock.sendall(b"GET /api/v1/events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    for sock in socks:
        try:
            status = sock.recv(4096).split(b" ", 2)[1].decode() or "closed"
        except (OSError, IndexError):
            status = "closed"
        heads[status] = heads.get(status, 0) + 1
    return socks, heads


def _bombard(port: int, token: str, stop: threading.Event, tally: dict[str, int]) -> None:
    headers = {"Content-Type": "application/json", "Authorization": f"Bearer {token}"}
    while not stop.is_set():
        for route in ("symbols", "forces"):
            for bomb in BOMBS:
                conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
                try:
                    conn.request("PUT", f"/api/v1/{route}/hold", bomb, headers)
                    status = str(conn.getresponse().status)
                except (OSError, http.client.HTTPException):
                    status = "error"
                finally:
                    conn.close()
                tally[status] = tally.get(status, 0) + 1


async def _opcua(kind: str, url: str, size: Any, stop: Callable[[], Any]) -> dict[str, Any]:
    from asyncua import Client, ua

    logging.getLogger("asyncua").setLevel(logging.CRITICAL)
    tally: dict[str, Any] = {"errors": 0}
    clients: list[Client] = []
    try:
        if kind == "opcua_huge_read":
            client = Client(url, timeout=60)
            await client.connect()
            clients.append(client)
            params = ua.ReadParameters()
            params.NodesToRead = [ua.ReadValueId(NodeId=ua.NodeId(ua.Int32(2258)),
                                                 AttributeId=ua.AttributeIds.Value)] * size
            waiting = asyncio.ensure_future(asyncio.to_thread(stop))
            reads = 0
            while not waiting.done():
                try:
                    await client.uaclient.read(params)
                    reads += 1
                except Exception:  # a refusal is the server's answer: count it, go on
                    tally["errors"] += 1
                    await asyncio.sleep(0.05)
            tally["reads"] = reads
            return tally
        sessions, items = size
        for _ in range(sessions):
            try:
                client = Client(url, timeout=10)
                await client.connect()
                clients.append(client)
                nodes = await client.get_node(ua.NodeId(ua.Int32(2256))).get_children()
                subscription = await client.create_subscription(50, _Ignore())
                await subscription.subscribe_data_change((nodes * items)[:items])
            except Exception:
                tally["errors"] += 1
        tally["sessions"] = len(clients)
        await asyncio.to_thread(stop)
        return tally
    finally:
        for client in clients:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.disconnect(), 5)


def abuser_main(kind: str, ports: dict[str, int], quick: bool, conn: Connection,
                token: str = "", where: Placement | None = None) -> None:
    """One abuse: placed first (its threads inherit it), set up, send {"ready": ...}, hold
    until told to stop, send the tally."""
    from softplc.runtime.shared.procs import die_with_parent

    die_with_parent()
    placed = place(where or Placement(None))
    size: Any = SIZES[kind][0 if quick else 1]
    report: dict[str, Any] = {"kind": kind, "size": size, "placed": placed.words()}
    if kind.startswith("opcua"):
        url = f"opc.tcp://127.0.0.1:{ports['opcua']}"
        if kind == "opcua_idle":
            socks = _idle_sockets(ports["opcua"], size)
            conn.send({"ready": len(socks)})
            conn.recv()
            report["connected"] = len(socks)
            for sock in socks:
                sock.close()
        else:
            def stop() -> Any:
                conn.send({"ready": True})
                return conn.recv()
            report.update(asyncio.run(_opcua(kind, url, size, stop)))
    elif kind == "event_streams":
        socks, heads = _event_streams(ports["api"], size)
        conn.send({"ready": heads})
        conn.recv()
        report["answers"] = heads
        for sock in socks:
            sock.close()
    else:
        halt, tally = threading.Event(), dict[str, int]()
        thread = threading.Thread(target=_bombard, args=(ports["api"], token, halt, tally))
        thread.start()
        conn.send({"ready": True})
        conn.recv()
        halt.set()
        thread.join(30)
        report["answers"] = tally
    conn.send(report)


def _phase(kind: str | None, runtime: LiveRuntime, worker: LoadWorker, duration_s: float,
           quick: bool, realtime: Realtime, progress: Progress,
           remote: bool = True) -> dict[str, Any]:
    """One phase: the pollers (and the abuse `kind`, None: none) for `duration_s`; every
    client on the scan's CPU (`remote`) or on the services' (placement.py)."""
    where = "clients remote" if remote else "clients on the services' CPU"
    progress(f"isolation: {kind or 'no abuse'} ({where}), {duration_s:g} s")
    job = LoadJob(runtime.modbus_port, 1, duration_s, runtime.api_url, 0.01, registers=10)
    pollers = place(placement.clients(realtime, remote), worker.pid).words()
    if kind is None:
        before = _cpu(runtime, 0)
        return {"load": worker.run(job), "cpu_s": _cpu(runtime, 0, before), "pollers": pollers}
    assert runtime.opcua_port is not None and runtime.api_port is not None
    ports = {"opcua": runtime.opcua_port, "api": runtime.api_port}
    here, there = _CTX.Pipe()
    token = ""
    with contextlib.suppress(OSError):  # the owner's key, as opcuabench reads it
        token = (Path(runtime._state_dir.name) / "api_token").read_text().strip()
    proc = _CTX.Process(target=abuser_main, name=f"softplc-bench-{kind}", daemon=True,
                        args=(kind, ports, quick, there, token,
                              placement.abuser(realtime, remote)))
    proc.start()
    try:
        if not here.poll(180):
            raise RuntimeError(f"the {kind} abuser did not get ready")
        ready = here.recv()
        before = _cpu(runtime, int(proc.pid or 0))
        load = worker.run(job)
        cpu = _cpu(runtime, int(proc.pid or 0), before)
        here.send("stop")
        report = here.recv() if here.poll(60) else {"error": "no report"}
    finally:
        proc.join(10)
        if proc.is_alive():
            proc.kill()
    return {"load": load, "cpu_s": cpu, "pollers": pollers,
            "abuse": {**report, "ready": ready.get("ready")}}


def _cpu(runtime: LiveRuntime, abuser: int,
         before: dict[str, float] | None = None) -> dict[str, float]:
    """CPU seconds used so far by each service process and the abuser (pid 0: none), or
    since `before`."""
    pids = {s.name: int(s.proc.pid) for s in runtime.supervisor.services if s.proc is not None}
    now = {name: cpu_s(pid) for name, pid in {**pids, "abuser": abuser}.items() if pid}
    return {k: round(v - (before or {}).get(k, 0.0), 3) for k, v in now.items()}


def _figures(phase: dict[str, Any], record: Any) -> dict[str, Any]:
    load = phase["load"]
    scans = window_figures(record.window(load["t0_ns"], load["t1_ns"]))
    return {**phase, "scan": scans, "modbus_p99_us": load["latency_us"]["p99"],
            "http_p99_us": load["http"]["latency_us"]["p99"],
            "scan_p99_us": scans["lateness_us"]["p99"],
            "errors": load["errors"] + load["http"]["errors"]}


def run(quick: bool, progress: Progress, *, duration_s: float | None = None,
        realtime: Realtime | None = None) -> dict[str, Any]:
    duration = duration_s if duration_s is not None else (2.0 if quick else 15.0)
    realtime = recommended() if realtime is None else realtime
    load_before = os.getloadavg()
    result: dict[str, Any] = {"duration_s": duration, "mode": "quick" if quick else "full",
                              "sizes": {k: v[0 if quick else 1] for k, v in SIZES.items()},
                              "program": "programs/transport.yaml (plant transport, started)"}
    progress(f"isolation: floor (empty loop) at 1 ms, {duration:g} s")
    floor = window_figures(run_floor(1_000_000, duration, realtime))
    phases: dict[str, dict[str, Any]] = {}
    runtime = LiveRuntime(period_ns=1_000_000, capacity_s=len(RUNS) * (duration + 90) + 120,
                          realtime=realtime, opcua=True)
    try:
        runtime.start()
        runtime.wait_for_state("RUNNING")
        time.sleep(SETTLE_S)
        with LoadWorker() as worker:
            for name, kind, remote in RUNS:  # a baseline just before each: the machine drifts
                phases[f"none_before_{name}"] = _phase(None, runtime, worker, duration, quick,
                                                       realtime, progress, remote)
                phases[name] = _phase(kind, runtime, worker, duration, quick, realtime,
                                      progress, remote)
        record = runtime.stop()
    finally:
        runtime.stop()
    assert record is not None
    figures = {name: _figures(phase, record) for name, phase in phases.items()}
    result.update(floor_1ms=floor, phases=figures)
    result["scan_p99_over_floor_max"] = ratio(
        max(figures[name]["scan_p99_us"] for name in figures), floor["lateness_us"]["p99"])
    result["scan_p99_ratio_none_over_floor"] = ratio(
        max(figures[f"none_before_{name}"]["scan_p99_us"] for name, _, _ in RUNS),
        floor["lateness_us"]["p99"])
    for what in ("modbus", "http", "scan"):
        ratios = {name: ratio(figures[name][f"{what}_p99_us"],
                              figures[f"none_before_{name}"][f"{what}_p99_us"])
                  for name, _, _ in RUNS}
        for name, value in ratios.items():
            result[f"{what}_p99_ratio_{name}"] = value
        for suffix, names in (("", ABUSES), ("_local", [f"{k}_local" for k in LOCAL])):
            known = [v for name, v in ratios.items() if name in names and v is not None]
            result[f"{what}_p99_ratio_max{suffix}"] = max(known) if known else None
    result["load_average_1m"] = [load_before[0], os.getloadavg()[0]]
    return result
