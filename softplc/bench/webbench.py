"""Benchmark section `web`: what open operator pages cost the scan, and what a page receives.

Three page clients (three readers of the page's live stream, `GET /api/v1/live`, at the
page's rate, in a process of their own as browsers would be) against the transport program
at 1 ms and 10 ms, beside the empty-loop floor of the same run.
Keys: `p99_ratio_over_floor_1ms` (scan p99 lateness with the pages open / the floor's),
`p99_ratio_over_idle_1ms` (the same runtime just before the pages opened) and
`bytes_per_s_per_page_1ms`, `bytes_per_s_per_page_10ms`, `frames_per_s_per_page_*`.
Owns: the page readers and the section's keys. Does not know: how the runtime starts (live.py).
"""

from __future__ import annotations

import http.client
import os
import threading
import time
from multiprocessing.connection import Connection
from typing import Any

from softplc.bench.live import LiveRuntime, run_floor
from softplc.bench.load import client_process
from softplc.bench.measure import Progress, ratio
from softplc.bench.scanbench import SETTLE_S, window_figures
from softplc.runtime.realtime import Realtime, recommended

PAGES = 3


def _read(port: int, duration_s: float, out: list[tuple[int, int]]) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
    received = frames = 0
    try:
        conn.request("GET", "/api/v1/live")
        response = conn.getresponse()
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            line = response.readline()
            if not line:
                break
            received += len(line)
            frames += line.startswith(b"data: ")
    finally:
        conn.close()
    out.append((received, frames))


def pages_main(port: int, pages: int, duration_s: float, results: Connection) -> None:
    """The page clients' process: `pages` streams read for `duration_s`, then the totals."""
    out: list[tuple[int, int]] = []
    t0 = time.monotonic_ns()
    threads = [threading.Thread(target=_read, args=(port, duration_s, out)) for _ in range(pages)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(duration_s + 10)
    results.send({"t0_ns": t0, "t1_ns": time.monotonic_ns(), "pages": len(out),
                  "bytes": sum(b for b, _ in out), "frames": sum(f for _, f in out)})


def _pages(port: int, duration_s: float, realtime: Realtime) -> dict[str, Any]:
    return client_process(pages_main, (port, PAGES, duration_s), "web-pages", realtime,
                          duration_s + 30, "the page clients")


def _period(period_ms: int, duration_s: float, realtime: Realtime,
            progress: Progress) -> dict[str, Any]:
    runtime = LiveRuntime(period_ns=period_ms * 1_000_000, capacity_s=2 * duration_s + 60,
                          realtime=realtime, modbus=False)
    try:
        progress(f"web: transport at {period_ms} ms with {PAGES} page clients, {duration_s:g} s")
        runtime.start()
        runtime.wait_for_state("RUNNING")
        time.sleep(SETTLE_S)
        assert runtime.api_port is not None
        idle_from = time.monotonic_ns()  # the same runtime without pages: what they add
        time.sleep(duration_s / 2)
        idle_to = time.monotonic_ns()
        pages = _pages(runtime.api_port, duration_s, realtime)
        record = runtime.stop()
    finally:
        runtime.stop()
    assert record is not None
    seconds = (pages["t1_ns"] - pages["t0_ns"]) / 1e9
    per_page = max(pages["pages"], 1)
    return {**window_figures(record.window(pages["t0_ns"], pages["t1_ns"])), "pages": pages,
            "idle": window_figures(record.window(idle_from, idle_to)),
            "bytes_per_s_per_page": pages["bytes"] / seconds / per_page,
            "frames_per_s_per_page": pages["frames"] / seconds / per_page}


def run(quick: bool, progress: Progress, *, duration_s: float | None = None,
        periods_ms: tuple[int, ...] = (1, 10), realtime: Realtime | None = None
        ) -> dict[str, Any]:
    duration = duration_s if duration_s is not None else (1.5 if quick else 20.0)
    realtime = recommended() if realtime is None else realtime
    load_before = os.getloadavg()
    result: dict[str, Any] = {"duration_s": duration, "pages": PAGES,
                              "program": "programs/transport.yaml (plant transport, started)"}
    progress(f"web: floor (empty loop) at 1 ms, {duration:g} s")
    floor = window_figures(run_floor(1_000_000, duration, realtime))
    result["floor_1ms"] = floor
    for period_ms in periods_ms:
        run_ = _period(period_ms, duration, realtime, progress)
        result[f"pages_{period_ms}ms"] = run_
        result[f"bytes_per_s_per_page_{period_ms}ms"] = run_["bytes_per_s_per_page"]
        result[f"frames_per_s_per_page_{period_ms}ms"] = run_["frames_per_s_per_page"]
    if 1 in periods_ms:
        result["p99_ratio_over_floor_1ms"] = ratio(
            result["pages_1ms"]["lateness_us"]["p99"], floor["lateness_us"]["p99"])
        result["overruns_1ms"] = result["pages_1ms"]["overruns"]
        result["p99_ratio_over_idle_1ms"] = ratio(
            result["pages_1ms"]["lateness_us"]["p99"],
            result["pages_1ms"]["idle"]["lateness_us"]["p99"])
    result["load_average_1m"] = [load_before[0], os.getloadavg()[0]]
    return result
