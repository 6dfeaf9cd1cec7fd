"""Benchmark section `scan`: scan timing of the transport program on its simulated plant, in
its own scan process as in production, beside the floor (the empty loop of the same
scheduler, same clock), idle and loaded (Modbus pollers and an HTTP status poller served by
the communication process), at 1 ms and 10 ms periods.

Owns: the sequence of runs, window figures, histograms, the section's keys.
Does not know: how the processes are started (live.py) or the clients work (load.py).
"""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from softplc.bench import simbench
from softplc.bench.live import LiveRuntime, ScanRecord, run_floor
from softplc.bench.load import LoadJob, LoadWorker
from softplc.bench.measure import Progress, figures, ratio
from softplc.runtime.realtime import Realtime, keep_off_scan_cpu, recommended

# One set of bin edges for every histogram (µs, logarithmic): runs can be overlaid.
HISTOGRAM_EDGES_US = [0.0, *np.geomspace(1.0, 100_000.0, 51).round(3).tolist()]
SETTLE_S = 0.5  # after RUNNING: the first scans page in code and data


def histogram(late_ns: np.ndarray) -> dict[str, list[float] | list[int]]:
    """Lateness counts over HISTOGRAM_EDGES_US; later samples count in the last bin."""
    edges = np.asarray(HISTOGRAM_EDGES_US)
    values = np.clip(late_ns / 1000.0, 0.0, edges[-1] - 1e-9)
    counts, _ = np.histogram(values, bins=edges)
    return {"edges_us": HISTOGRAM_EDGES_US, "counts": counts.astype(int).tolist()}


def window_figures(record: ScanRecord) -> dict[str, Any]:
    """Lateness and execution figures (µs) and skipped slots of the scans of one window."""
    late = figures(record.late_ns / 1000.0)
    return {
        "scans": int(record.late_ns.size), "overruns": int(record.missed.sum()),
        "lateness_us": {"p50": late.median, "p99": late.p99, "p999": late.p999,
                        "max": late.max, "mean": late.mean},
        "exec_us": figures(record.exec_ns / 1000.0).as_dict(),
    }


def _measure_period(period_ms: int, duration_s: float, worker: LoadWorker, clients: int,
                    http_interval_s: float, progress: Progress,
                    out: dict[str, Any], hists: dict[str, Any], realtime: Realtime) -> None:
    period_ns = period_ms * 1_000_000
    progress(f"scan: floor (empty loop) at {period_ms} ms, {duration_s:g} s")
    floor = run_floor(period_ns, duration_s, realtime)
    out[f"floor_{period_ms}ms"] = window_figures(floor)
    hists[f"floor_{period_ms}ms"] = histogram(floor.late_ns)
    runtime = LiveRuntime(period_ns=period_ns, capacity_s=2 * duration_s + 60,
                          realtime=realtime)
    try:
        progress(f"scan: transport at {period_ms} ms, starting the runtime")
        runtime.start()
        runtime.wait_for_state("RUNNING")
        obtained = runtime.status().get("realtime", "?")  # what the scan process was granted
        time.sleep(SETTLE_S)
        progress(f"scan: transport at {period_ms} ms, idle, {duration_s:g} s")
        idle_from = time.monotonic_ns()
        time.sleep(duration_s)
        idle_to = time.monotonic_ns()
        progress(f"scan: transport at {period_ms} ms, {clients} Modbus clients + HTTP, "
                 f"{duration_s:g} s")
        load = worker.run(LoadJob(runtime.modbus_port, clients, duration_s, runtime.api_url,
                                  http_interval_s))
        record = runtime.stop()
    finally:
        runtime.stop()
    assert record is not None
    idle = record.window(idle_from, idle_to)
    loaded = record.window(load["t0_ns"], load["t1_ns"])
    out[f"idle_{period_ms}ms"] = {**window_figures(idle), "realtime": obtained}
    out[f"loaded_{period_ms}ms"] = {**window_figures(loaded), "load": load,
                                    "realtime": obtained}
    hists[f"idle_{period_ms}ms"] = histogram(idle.late_ns)
    hists[f"loaded_{period_ms}ms"] = histogram(loaded.late_ns)


def run(quick: bool, progress: Progress, *, duration_s: float | None = None,
        periods_ms: tuple[int, ...] = (1, 10), clients: int = 4,
        http_interval_s: float = 0.01, realtime: Realtime | None = None) -> dict[str, Any]:
    """Floor, idle and loaded runs per period, the scan and the floor both scheduled as
    `realtime` says (default: SCHED_FIFO on a CPU of its own, as docs/realtime.md
    recommends; `Realtime()` for normal scheduling); keys `p99_ratio_loaded_over_floor_1ms` and
    `overruns_loaded_1ms` (and the same for every period measured)."""
    duration = duration_s if duration_s is not None else (1.0 if quick else 30.0)
    realtime = recommended() if realtime is None else realtime
    configs: dict[str, Any] = {}
    hists: dict[str, Any] = {}
    load_before = os.getloadavg()
    with LoadWorker() as worker:
        keep_off_scan_cpu(worker.pid, realtime)  # the HMI load runs beside the PLC, as it would
        for period_ms in periods_ms:
            _measure_period(period_ms, duration, worker, clients, http_interval_s, progress,
                            configs, hists, realtime)
    result: dict[str, Any] = {
        "duration_s": duration, "clients": clients, "http_interval_s": http_interval_s,
        "program": "programs/transport.yaml (plant transport, started)",
        "load_average_1m": [load_before[0], os.getloadavg()[0]],
        "configs": configs, "histograms": hists,
        "realtime": f"priority {realtime.priority}, cpu {realtime.cpu}",
    }
    # The scan's execution in the live loop over the firing round of the same net, measured
    # in this run (issue 15.5): what the shell around the round costs.
    progress("scan: firing-round baseline (transport, in process)")
    round_us = simbench.round_median_us(2_000 if quick else 20_000)
    first = min(periods_ms)
    exec_us = configs[f"idle_{first}ms"]["exec_us"]["median"]
    result["round_median_us"] = round_us
    result["exec_median_us"] = exec_us
    result["exec_over_round"] = ratio(exec_us, round_us)
    for period_ms in periods_ms:
        floor_p99 = configs[f"floor_{period_ms}ms"]["lateness_us"]["p99"]
        for kind in ("idle", "loaded"):
            p99 = configs[f"{kind}_{period_ms}ms"]["lateness_us"]["p99"]
            result[f"p99_ratio_{kind}_over_floor_{period_ms}ms"] = ratio(p99, floor_p99)
        result[f"overruns_loaded_{period_ms}ms"] = configs[f"loaded_{period_ms}ms"]["overruns"]
    return result
