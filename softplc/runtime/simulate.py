"""Simulation in virtual time: the same scans as the real loop, as fast as the machine allows.

Owns: `simulate()` and its report (the `softplc simulate --json` object).
Does not know: processes, sockets, the real clock (a virtual clock jumps deadline to deadline).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softplc.core.net import CompiledNet
from softplc.devices.sim import SimDriver
from softplc.runtime.runner import boot
from softplc.runtime.trace import TraceWriter


def simulate(net: CompiledNet, duration_ns: int, period_ns: int = 10_000_000, seed: int = 0,
             trace_path: str | Path | None = None, plant: str | None = None) -> dict[str, Any]:
    """Run `net` on its simulated plant for `duration_ns` of virtual time."""
    if period_ns <= 0:
        raise ValueError("period must be positive")
    trace = TraceWriter(trace_path)
    runner, commands = boot(net, seed, start=True, trace=trace, plant=plant)
    scans = duration_ns // period_ns
    try:
        for k in range(scans):
            runner.step(k * period_ns, commands if k == 0 else ())
    finally:
        runner.close()
    plc = runner.plc
    plants = [d.plant.report().as_dict() for d in runner.drivers if isinstance(d, SimDriver)]
    outputs = {s.name: plc.image.get(s.address) for s in net.io.symbols.values()
               if s.direction.value != "in"}
    return {
        "program": net.name,
        "program_hash": net.program_hash,
        "scans": scans,
        "duration_s": scans * period_ns / 1e9,
        "period_ms": period_ns / 1e6,
        "seed": seed,
        "state": plc.state.name,
        "fired": dict(sorted(runner.fired_counts.items())),
        "marking": plc.marking(),
        "outputs_final": outputs,
        "plant": plants[0] if len(plants) == 1 else plants,
        "diagnostics": plc.engine.diagnostics if plc.engine else [],
        "trace_sha256": trace.sha256,
    }
