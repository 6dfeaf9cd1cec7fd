"""A trace walked scan by scan: replayed into a fresh PLC, the PLC shown after each scan.

Owns: `walk`, which feeds a trace's inputs, commands, HMI writes and observations back into
a PLC as `softplc replay` does (debug/replay.py) and yields each scan with the PLC after
it, stopping at the first scan that does not reproduce; and the capture of one scan's firing
round as it ran (the marking it started from, its image and events, time and forces), which
`softplc why --trace` explains (core/why.py). Used by the VCD export (debug/vcd.py) too.
Does not know: what the scans are used for, devices, clocks.
"""

from __future__ import annotations

import contextlib
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softplc.core.context import ScanContext
from softplc.core.errors import SoftplcError
from softplc.core.expr import EvalContext
from softplc.core.image import ProcessImage, parse_address
from softplc.core.net import CompiledNet, NetState
from softplc.core.plc import Plc
from softplc.core.result import ScanResult
from softplc.core.scan import scan
from softplc.core.snapshot import HmiWrite
from softplc.core.why import Why, run_round, why
from softplc.debug.replay import apply_inputs, trace_commands
from softplc.runtime.runner import observed_from
from softplc.runtime.trace import image_digest, read_trace


class TraceDiverges(SoftplcError, ValueError):
    """The trace does not replay with this program (another program, or another version)."""


@dataclass(frozen=True, slots=True)
class Capture:
    """A firing round's inputs, copied as the scan handed them to the engine."""

    net: CompiledNet
    state: NetState
    ctx: ScanContext
    now_ns: int
    forced: dict[str, int]


@dataclass(frozen=True, slots=True)
class Scanned:
    """One scan of the trace: its record, the PLC after it, and its round when captured."""

    record: dict[str, Any]
    plc: Plc
    result: ScanResult
    capture: Capture | None


def walk(trace_path: str | Path, net: CompiledNet,
         capture: Collection[int] = ()) -> Iterator[Scanned]:
    """Each scan of the trace, replayed with `net`; the rounds of the scans numbered in
    `capture` are captured. Raises TraceDiverges at a scan that does not reproduce, OSError
    and ValueError for an unreadable trace."""
    plc = Plc.empty(ProcessImage(net.io.sizes))
    inputs = ProcessImage(net.io.sizes)
    drivers = list(net.io.drivers)
    for record in read_trace(trace_path):
        apply_inputs(inputs, record.get("in", {}))
        commands, _ = trace_commands(record, net)
        hmi = [HmiWrite(parse_address(a), tuple(v)) for a, v in record.get("hmi", [])]
        observed = observed_from(record.get("obs", {}), drivers)
        rounds: list[Capture] = []
        with _capturing(plc, rounds) if int(record["k"]) in capture else contextlib.nullcontext():
            result = scan(plc, inputs, int(record["t"]), commands, hmi, observed)
        if image_digest(result.outputs) != record["out"] or \
                list(result.fired) != record.get("fired", []):
            raise TraceDiverges(
                f"scan {record['k']} does not replay with program {net.name} "
                f"{net.program_hash[:12]}: recorded fired {record.get('fired', [])}, replay "
                f"fired {list(result.fired)} (was the trace recorded with this program?)")
        yield Scanned(record, plc, result, rounds[0] if rounds else None)


@contextlib.contextmanager
def _capturing(plc: Plc, rounds: list[Capture]) -> Iterator[None]:
    """Copy what the round of this one scan is given: the round's inputs exactly as the scan
    builds them (commands applied, HMI writes, forces, events). Only this PLC's engine is
    wrapped (an attribute of the instance, for the length of one scan() call, in a CLI
    process), so the scan's own path stays as it is for every scan nobody asks about."""
    engine = plc.engine
    if engine is None:  # no program: the scan runs no round
        yield
        return
    original = engine.fire_round

    def fire_round(ctx: EvalContext, now_ns: int, changed: Collection[str] = (),
                   only: int | None = None) -> Any:
        if isinstance(ctx, ScanContext):
            copied = ScanContext(ctx.image.copy(), ctx.prev.copy(), dict(ctx.locations),
                                 frozenset(ctx.events), ctx.typed, ctx.scaled)
            rounds.append(Capture(engine.net, engine.state.copy(), copied, now_ns,
                                  plc.forces.values()))
        return original(ctx, now_ns, changed, only)

    engine.fire_round = fire_round  # type: ignore[method-assign]
    try:
        yield
    finally:
        del engine.fire_round  # the class's method again


def why_at(trace_path: str | Path, net: CompiledNet, name: str, at_scan: int) -> Why:
    """Why transition `name` fired or not in the round of scan `at_scan` of the trace.
    KeyError for an unknown transition; ValueError when that scan ran no round or the trace
    has no such scan (TraceDiverges when it does not replay with `net`)."""
    net.transition(name)  # an unknown name fails before the trace is read
    for scanned in walk(trace_path, net, capture=(at_scan,)):
        if int(scanned.record["k"]) != at_scan:
            continue
        cap = scanned.capture
        if cap is None:
            raise ValueError(f"scan {at_scan} ran no firing round (state "
                             f"{scanned.record.get('state')}): nothing fires in it")
        return why(run_round(cap.net, cap.state, cap.ctx, cap.now_ns, cap.forced), name)
    raise ValueError(f"the trace has no scan {at_scan}")
