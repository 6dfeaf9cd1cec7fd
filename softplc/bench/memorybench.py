"""Benchmark section `memory`: resident memory (VmRSS) of the scan, communication and compile
processes, unchanged from production, before and after a soak: transport at 10 ms with the
loaded clients (Modbus pollers and an HTTP status poller) for the whole soak.

Owns: the soak sequence, RSS sampling, the section's keys.
Does not know: how the processes are started (live.py) or the clients work (load.py).
"""

from __future__ import annotations

import os
import time
from typing import Any

from softplc.bench.live import LiveRuntime, rss_kib
from softplc.bench.load import LoadJob, LoadWorker
from softplc.bench.measure import Progress
from softplc.runtime.shared.procs import children

SETTLE_S = 1.0


def _rss_mb(runtime: LiveRuntime) -> dict[str, float]:
    scan = rss_kib(runtime.scan.pid) / 1024
    comm = sum(rss_kib(service.proc.pid) for service in runtime.supervisor.services
               if service.proc is not None) / 1024  # every service process
    compiler = sum(rss_kib(pid) for pid in children(runtime.scan.pid)) / 1024
    return {"scan": round(scan, 2), "comm": round(comm, 2), "compile": round(compiler, 2),
            "total": round(scan + comm + compiler, 2)}


def run(quick: bool, progress: Progress, *, duration_s: float | None = None,
        clients: int = 4, http_interval_s: float = 0.01, samples: int = 30) -> dict[str, Any]:
    """RSS at the start and end of the soak and along it; key `rss_mb` (both, at the end)."""
    duration = duration_s if duration_s is not None else (60.0 if quick else 600.0)
    load_before = os.getloadavg()
    # record=False: the production scan process, so no benchmark array adds to its memory.
    runtime = LiveRuntime(period_ns=10_000_000, record=False)
    curve: list[dict[str, float]] = []
    try:
        progress("memory: starting the runtime (transport at 10 ms)")
        runtime.start()
        runtime.wait_for_state("RUNNING")
        time.sleep(SETTLE_S)
        start = _rss_mb(runtime)
        with LoadWorker() as worker:
            worker.submit(LoadJob(runtime.modbus_port, clients, duration, runtime.api_url,
                                  http_interval_s))
            began = time.monotonic()
            step_s = duration / samples
            while (elapsed := time.monotonic() - began) < duration:
                progress(f"memory: soak with {clients} Modbus clients + HTTP, "
                         f"{elapsed:.0f}/{duration:g} s")
                curve.append({"t_s": round(elapsed, 2), **_rss_mb(runtime)})
                time.sleep(min(step_s, max(0.0, duration - elapsed)))
            load = worker.result()
        end = _rss_mb(runtime)
        status = runtime.status()
    finally:
        runtime.stop()
    return {
        "duration_s": duration, "period_ms": 10, "clients": clients,
        "http_interval_s": http_interval_s,
        "load_average_1m": [load_before[0], os.getloadavg()[0]],
        "start_mb": start, "end_mb": end, "growth_mb": round(end["total"] - start["total"], 2),
        "curve": curve, "rss_mb": end["total"],
        "modbus_requests": load["requests"], "modbus_errors": load["errors"],
        "http_requests": load.get("http", {}).get("requests", 0),
        "plc_state_at_end": status.get("state"),
        "overruns": status.get("timing", {}).get("overruns"),
    }
