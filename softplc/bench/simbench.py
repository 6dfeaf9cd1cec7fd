"""Benchmark section `simulate` and the firing-round baseline of `scan.exec_over_round`.

Owns: `simulate.realtime_factor` (simulated time / wall time of `softplc simulate` for both
case studies at a 10 ms period, the slower of the two as the headline) and the median
firing-round time of the transport program on its simulated plant, measured in this process
as the denominator of the scan section's `exec_over_round`.
Does not know: the live loop (scanbench.py measures the scan execution time there).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from softplc.bench.measure import Progress, figures
from softplc.core.engine import Engine, Step
from softplc.program.compiler import compile_file
from softplc.runtime.offline.simulate import simulate
from softplc.runtime.runner import boot

PROGRAMS = Path(__file__).resolve().parents[2] / "programs"
CASE_STUDIES = ("transport", "drilling")
PERIOD_NS = 10_000_000


def realtime_factors(sim_s: float, progress: Progress) -> dict[str, Any]:
    """`simulate()` of each case study for `sim_s` seconds of virtual time at 10 ms; the best
    of three runs each (the machine is shared: the best run is the least disturbed one)."""
    out: dict[str, Any] = {}
    for name in CASE_STUDIES:
        progress(f"simulate: {name}, {sim_s:g} s of virtual time at 10 ms")
        net = compile_file(PROGRAMS / f"{name}.yaml")
        walls = []
        for _ in range(3):
            began = time.perf_counter()
            report = simulate(net, int(sim_s * 1e9), PERIOD_NS, 0, None, name)
            walls.append(time.perf_counter() - began)
        wall = min(walls)
        out[name] = {"scans": report["scans"], "wall_s": round(wall, 4),
                     "us_per_scan": round(wall / report["scans"] * 1e6, 2),
                     "realtime_factor": round(sim_s / wall, 1)}
    return out


def round_median_us(scans: int = 20_000) -> float:
    """Median time (µs) of the engine's firing round for the transport program on its
    simulated plant at 1 ms, measured around Engine.fire_round inside the same scans the
    live loop runs (ScanRunner.step)."""
    net = compile_file(PROGRAMS / "transport.yaml")
    runner, commands = boot(net, 0, start=True, plant="transport")
    samples = np.zeros(scans, dtype=np.int64)
    taken = 0

    def timed(engine: Engine) -> None:
        inner = engine.fire_round

        def fire_round(*args: Any, **kwargs: Any) -> Step:
            nonlocal taken
            began = time.perf_counter_ns()
            step = inner(*args, **kwargs)
            if taken < scans:
                samples[taken] = time.perf_counter_ns() - began
                taken += 1
            return step

        engine.fire_round = fire_round  # type: ignore[method-assign]

    try:
        runner.step(0, commands)
        assert runner.plc.engine is not None
        timed(runner.plc.engine)
        k = 1
        while taken < scans:
            runner.step(k * 1_000_000)
            k += 1
    finally:
        runner.close()
    return figures(samples / 1000.0).median


def run(quick: bool, progress: Progress) -> dict[str, Any]:
    sim_s = 60.0 if quick else 600.0
    studies = realtime_factors(sim_s, progress)
    return {"virtual_s": sim_s, "period_ms": PERIOD_NS / 1e6, "case_studies": studies,
            "realtime_factor": min(s["realtime_factor"] for s in studies.values())}
