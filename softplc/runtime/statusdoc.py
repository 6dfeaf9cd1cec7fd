"""The scan loop's status, as people and other processes read it.

Owns: the status board document (`softplc status`, the HTTP API, the operator's page) and the
fixed-size Status of every published snapshot, both read between scans off a LoopView: what a
scan loop shows of itself (runtime/loop.py's ScanLoop is one; this module does not import it).
Does not know: how they are published (runtime/shared/board.py, runtime/shared/shm.py), the
loop's workings.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any, Protocol
from weakref import WeakKeyDictionary

from softplc.core.context import ScanContext
from softplc.core.image import ProcessImage
from softplc.core.judge import CycleWatchdog
from softplc.core.lifecycle import PlcState, Stage
from softplc.core.net import CompiledNet, NetState
from softplc.core.present import shown
from softplc.core.snapshot import Status
from softplc.core.symbols import scalings
from softplc.core.waiting import Waits
from softplc.runtime import netview
from softplc.runtime.bootkeeper import BootKeeper
from softplc.runtime.clock import Clock
from softplc.runtime.compileproc import CompileProcess
from softplc.runtime.config import LoopConfig
from softplc.runtime.download import Downloads
from softplc.runtime.realtime import HelperThreads
from softplc.runtime.retain.writer import RetainWriter
from softplc.runtime.runner import ScanRunner
from softplc.runtime.stats import TimingStats, TimingSummary


class LoopView(Protocol):
    """What a scan loop shows of itself for status: read-only, between scans."""

    @property
    def config(self) -> LoopConfig: ...
    @property
    def runner(self) -> ScanRunner: ...
    @property
    def clock(self) -> Clock: ...
    @property
    def stats(self) -> TimingStats: ...
    @property
    def summary(self) -> TimingSummary: ...
    @property
    def stalls(self) -> int: ...
    @property
    def longest_gap_ns(self) -> int: ...
    @property
    def budget_ns(self) -> int: ...
    @property
    def watchdog(self) -> CycleWatchdog: ...
    @property
    def internal_errors(self) -> int: ...
    @property
    def start_mode(self) -> str: ...
    @property
    def start_reason(self) -> str: ...
    @property
    def realtime(self) -> str: ...
    @property
    def helpers(self) -> HelperThreads: ...
    @property
    def boot(self) -> BootKeeper: ...
    @property
    def analysis(self) -> dict[str, Any] | None: ...
    @property
    def retain(self) -> RetainWriter | None: ...
    @property
    def compiler(self) -> CompileProcess | None: ...
    @property
    def downloads(self) -> Downloads: ...
    @property
    def events(self) -> Sequence[dict[str, Any]]: ...


def document(loop: LoopView) -> dict[str, Any]:
    """The status board of `loop`: what `softplc status` and the HTTP API show."""
    plc = loop.runner.plc
    timing: dict[str, Any] = dict(loop.summary.as_dict())
    timing["p99_lateness_us"] = timing.get("lateness_p99_us", 0)
    timing["overruns"] = loop.stats.overruns
    timing["stalls"] = loop.stalls
    timing["longest_gap_us"] = loop.longest_gap_ns // 1000
    net = plc.net
    # The net's clock (docs/debug.md, the time rule): while paused it stands at the next
    # scan's net time, so countdowns and live `why` stand still and agree with a step.
    now_ns = loop.clock.now_ns()
    net_now_ns = now_ns - plc.debug.frozen_shift(now_ns)
    symbols = {} if net is None else _symbols(net, plc.image)
    return {
        "state": plc.state.name, "program": net.name if net else None,
        "program_hash": net.program_hash if net else None, "scan_count": plc.scan_count,
        "period_us": loop.config.period_ns // 1000, "marking": plc.marking(),
        "timing": timing, "fault_code": int(plc.fault_code),
        "fault_name": plc.fault_code.name.lower(),
        "fault_reason": plc.fault_reason, "devices": loop.runner.device_report(),
        "start_mode": loop.start_mode,
        "start_reason": loop.start_reason, "program_source": loop.boot.source,
        "start_program": loop.boot.started,  # compiled once by `softplc run`, or here
        "boot_policy": loop.config.boot_policy,
        "boot_policy_source": loop.config.boot_policy_source,
        "realtime": loop.realtime, "helper_threads": loop.helpers.said,
        "restarts": loop.config.restarts, "restart_reason": loop.config.restart_reason,
        "scan_pid": os.getpid(),
        "on_stall": loop.config.on_stall, "watchdog_ms": loop.budget_ns / 1e6,
        "watchdog_sensitivity": loop.watchdog.sensitivity,
        "watchdog_hard_ms": loop.watchdog.hard_ns / 1e6,
        "stall_fault_ms": max(loop.config.stall_fault_ns, loop.budget_ns) / 1e6,
        "internal_errors": loop.internal_errors, "analysis": loop.analysis,
        "boot_problem": loop.boot.problem,
        "retain": loop.retain.info() if loop.retain else None,
        "compile_process": loop.compiler.info() if loop.compiler else None,
        "download_steps": loop.downloads.log.as_dict(),  # between scans (runtime/steplog.py)
        "health": {name: h.value for name, h in loop.runner.health().items()},
        "diagnostics": list(plc.engine.diagnostics[-20:]) if plc.engine else [],
        "diagnostic_count": plc.engine.diagnostic_count if plc.engine else 0,
        "tokens": _records(net, plc.engine.state if plc.engine else None),
        "symbols": symbols, "events": list(loop.events),
        "forced": plc.forces.shown(),  # forcing (docs/design.md section 10), typed
        # Why nothing moves (core/waiting.py): the longest waits and what blocks each.
        "waiting": waiting(loop, net_now_ns),
        # Memory symbols that kept a value from another program (docs/retain.md); null: none.
        "kept_across": plc.kept_across.as_dict() if plc.kept_across else None,
        # The operator's page (docs/web.md): structure cached per program, live state.
        "net": netview.structure(net) if net else None,
        "net_live": netview.live(net, plc.engine.state if plc.engine else None, net_now_ns,
                                 loop.runner.fired_counts),
        # Start-up (docs/faults.md): devices whose first input image has not arrived; while
        # any has not, a RUNNING PLC runs no firing round and its outputs stay safe.
        "waiting_for_io": bool(plc.waiting_io), "waiting_for_devices": list(plc.waiting_io),
        # Breakpoints (docs/debug.md): "breakpoints", "paused" (null: not paused), "steps_left".
        **plc.debug.as_dict(),
    }

_WAITS: WeakKeyDictionary[ScanRunner, Waits] = WeakKeyDictionary()


def waiting(loop: LoopView, net_now_ns: int) -> list[dict[str, Any]]:
    """The transitions the running net has waited on longest (net time: a pause stands
    still), with their blockers (docs/simulate.md, a reset with parts on the belts); []
    unless RUNNING with every device delivered. Observed at each document, between scans."""
    runner = loop.runner
    plc, waits = runner.plc, _WAITS.setdefault(runner, Waits())
    if plc.state is not PlcState.RUNNING or plc.waiting_io or plc.net is None \
            or plc.engine is None:
        waits.clear()
        return []
    state = plc.engine.state
    waits.observe(plc.net, state, net_now_ns, runner.fired_counts)
    ctx = ScanContext(plc.image, plc.prev, plc.locations, frozenset(), plc.typed,
                      scalings(plc.net.io))
    return [w.as_dict() for w in waits.longest(state, ctx, net_now_ns, plc.forces.values())]


def status(loop: LoopView) -> Status:
    """The fixed-size status of every snapshot (shared memory, Modbus status block)."""
    plc = loop.runner.plc
    return Status(plc.state, plc.scan_count, loop.stats.last_exec_ns // 1000,
                  loop.stats.max_exec_ns // 1000, int(loop.summary.lateness_p99_us),
                  loop.stats.overruns,
                  plc.net.program_hash if plc.net else "", int(plc.fault_code),
                  loop.config.period_ns // 1000, len(plc.forces), bool(plc.waiting_io),
                  plc.stage is Stage.SUSPENDED)


def _symbols(net: CompiledNet, image: ProcessImage) -> dict[str, dict[str, Any]]:
    """Every symbol's board entry: `value` as people read it (core/present.py: a negative
    int, a real, a scaled symbol's engineering value with its `unit` and `scale`), `raw` the
    bits its location holds (what the why route puts back into an image); the rest is fixed
    per program (runtime/netview.py)."""
    entries = {}
    for s, fixed in netview.described(net).symbols:
        raw = image.get(s.address)
        entry = entries[s.name] = dict(fixed)
        entry["value"], entry["raw"] = shown(s.type.value, raw, s.scaling), raw
    return entries


def _records(net: CompiledNet | None, state: NetState | None) -> dict[str, list[Any]]:
    """Coloured places' records (the first 20 of each), for status and the API."""
    if net is None or state is None:
        return {}
    return {net.place_names[p]: [dict(t) for t in records[:20]]
            for p, records in sorted(state.tokens.items()) if records}
