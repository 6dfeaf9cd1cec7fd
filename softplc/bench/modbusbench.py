"""Benchmark section `modbus`: our Modbus TCP slave (communication process, PLC scanning the
transport program at 1 ms) beside a plain pymodbus 3.16 ModbusTcpServer with a standard
SimDevice datastore, same machine, same run, same request mix (FC3 x 100 holding registers,
1 and 4 closed-loop clients in a separate process), alternating between the two servers.

Owns: the plain reference server process, the run order, the section's keys.
Does not know: how our slave answers (softplc.hmi), how the clients work (load.py).
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing as mp
import os
from multiprocessing.synchronize import Event
from typing import Any

from softplc.bench.live import LiveRuntime, ScanRecord, cpu_s, free_port
from softplc.bench.load import LoadJob, LoadWorker
from softplc.bench.measure import Progress, figures, ratio
from softplc.bench.scanbench import window_figures

_CTX = mp.get_context("spawn")
PLAIN_REGISTERS = 1000


async def _serve_plain(port: int, ready: Event, stop: Event) -> None:
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    # The documented 3.16 datastore (reference/pymodbus-3.16.md 1.2): id 0 answers any unit.
    device = SimDevice(id=0, simdata=(
        [SimData(0, values=[False] * 16, datatype=DataType.BITS)],
        [SimData(0, values=[False] * 16, datatype=DataType.BITS)],
        [SimData(0, values=list(range(PLAIN_REGISTERS)), datatype=DataType.REGISTERS)],
        [SimData(0, values=[0] * 16, datatype=DataType.REGISTERS)],
    ))
    server = ModbusTcpServer(device, address=("127.0.0.1", port))
    await server.serve_forever(background=True)
    ready.set()
    try:
        while not stop.is_set():
            await asyncio.sleep(0.1)
    finally:
        await server.shutdown()  # type: ignore[no-untyped-call]


def plain_server_main(port: int, ready: Event, stop: Event) -> None:
    from softplc.runtime.shared.procs import die_with_parent

    die_with_parent()
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    asyncio.run(_serve_plain(port, ready, stop))


class PlainServer:
    """The reference server in its own process, as ours runs in the communication process."""

    def __init__(self) -> None:
        self.port = free_port()
        self._stop = _CTX.Event()
        ready = _CTX.Event()
        self._proc = _CTX.Process(target=plain_server_main, args=(self.port, ready, self._stop),
                                  name="pymodbus-plain", daemon=True)
        self._ready = ready
        self._proc.start()

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        if not self._ready.wait(timeout_s):
            raise RuntimeError("the plain pymodbus server did not start")

    @property
    def pid(self) -> int:
        return int(self._proc.pid or 0)

    def close(self) -> None:
        self._stop.set()
        self._proc.join(10)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(5)


def _measure(worker: LoadWorker, port: int, pid: int, clients: int, duration_s: float,
             registers: int) -> dict[str, Any]:
    cpu_before = cpu_s(pid)
    result = worker.run(LoadJob(port, clients, duration_s, registers=registers,
                                keep_latencies=True))
    result["server_cpu_s"] = cpu_s(pid) - cpu_before
    return result


def _combine(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Rounds of one configuration as one: requests over total time, pooled latencies."""
    latencies = [x for p in parts for x in p["latencies_us"]]
    requests = sum(p["requests"] for p in parts)
    seconds = sum(p["duration_s"] for p in parts)
    cpu = sum(p["server_cpu_s"] for p in parts)
    lat = figures(latencies)
    return {"requests": requests, "duration_s": seconds, "requests_per_s": requests / seconds,
            "errors": sum(p["errors"] for p in parts),
            "first_error": next((p["first_error"] for p in parts if p["first_error"]), ""),
            "latency_us": {"p50": lat.median, "p99": lat.p99, "p999": lat.p999,
                           "max": lat.max, "mean": lat.mean},
            "server_cpu_us_per_request": ratio(cpu * 1e6, requests),
            "windows": [[p["t0_ns"], p["t1_ns"]] for p in parts]}


def run(quick: bool, progress: Progress, *, duration_s: float | None = None,
        clients: tuple[int, ...] = (1, 4), rounds: int | None = None,
        registers: int = 100) -> dict[str, Any]:
    """requests/s and latency of both servers; key `throughput_ratio_vs_pymodbus_4c`."""
    duration = duration_s if duration_s is not None else (0.75 if quick else 10.0)
    n_rounds = rounds if rounds is not None else (1 if quick else 2)
    load_before = os.getloadavg()
    parts: dict[str, list[dict[str, Any]]] = {}
    runtime = LiveRuntime(period_ns=1_000_000, capacity_s=4 * duration * len(clients) + 120)
    plain: PlainServer | None = None
    worker: LoadWorker | None = None
    try:
        progress("modbus: starting the runtime (transport at 1 ms) and plain pymodbus")
        plain, worker = PlainServer(), LoadWorker()  # both start while the runtime does
        runtime.start()
        plain.wait_ready()
        runtime.wait_for_state("RUNNING")
        assert runtime.modbus_port is not None and runtime.comm is not None
        servers = {"ours": (runtime.modbus_port, runtime.comm.pid),
                   "pymodbus": (plain.port, plain.pid)}
        for n in clients:
            for r in range(n_rounds):
                order = ["ours", "pymodbus"] if r % 2 == 0 else ["pymodbus", "ours"]
                for name in order:  # alternating: drift of the machine hits both alike
                    progress(f"modbus: {name}, {n} client(s), round {r + 1}/{n_rounds}, "
                             f"{duration / n_rounds:g} s")
                    port, pid = servers[name]
                    parts.setdefault(f"{name}_{n}c", []).append(
                        _measure(worker, port, pid, n, duration / n_rounds, registers))
        record = runtime.stop()
    finally:
        runtime.stop()
        if plain is not None:
            plain.close()
        if worker is not None:
            worker.close()
    result: dict[str, Any] = {"duration_s": duration, "rounds": n_rounds, "registers": registers,
                              "scan_period_ms": 1,
                              "load_average_1m": [load_before[0], os.getloadavg()[0]]}
    for key, runs in parts.items():
        result[key] = _combine(runs)
        if key.startswith("ours") and record is not None:
            result[key]["scan"] = _scan_meanwhile(record, result[key]["windows"])
    for n in clients:
        ours, plain_run = result[f"ours_{n}c"], result[f"pymodbus_{n}c"]
        result[f"throughput_ratio_vs_pymodbus_{n}c"] = ratio(ours["requests_per_s"],
                                                             plain_run["requests_per_s"])
        result[f"p99_latency_ratio_vs_pymodbus_{n}c"] = ratio(ours["latency_us"]["p99"],
                                                              plain_run["latency_us"]["p99"])
    return result


def _scan_meanwhile(record: ScanRecord, windows: list[list[int]]) -> dict[str, Any]:
    """What serving Modbus did to the scan meanwhile (same process layout as `run`)."""
    merged = record.window(*windows[0])
    for t0, t1 in windows[1:]:
        merged = merged.concat(record.window(t0, t1))
    return window_figures(merged)
