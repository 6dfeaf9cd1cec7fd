"""How a scan loop starts its program: warm from the newest usable retain snapshot of the
same program, else cold from the initial marking (docs/retain.md).

Owns: the start decision applied to a starting loop (`Starting`: what it may set) before its
first scan: the program's devices opened and the snapshot put in (warm), or the download
queued (cold); a snapshot that does not fit after all falls back to cold, with the reason;
a restart of a scan process that died paused at a breakpoint waits STOPPED.
Does not know: how snapshots are stored and chosen (runtime/retain/writer.py).
"""

from __future__ import annotations

import sys
from typing import Protocol

from softplc.core.lifecycle import Command, PlcState
from softplc.core.net import CompiledNet, persistent_places
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.symbols import persistent_memory
from softplc.runtime.clock import Clock
from softplc.runtime.config import LoopConfig
from softplc.runtime.prepare import Prepared
from softplc.runtime.retain.writer import (
    ContinuedClock,
    Loaded,
    RetainStore,
    RetainWriter,
    StartDecision,
    decide,
    load_plant,
    restore,
    restore_persistent,
)
from softplc.runtime.runner import ScanRunner
from softplc.runtime.shared.shm import SnapshotWriter


class Starting(Protocol):
    """What a starting scan loop lets the start decision set (runtime/loop.py's ScanLoop is
    one; this module does not import it)."""

    config: LoopConfig
    runner: ScanRunner
    writer: SnapshotWriter | None
    clock: Clock
    retain: RetainWriter | None
    retained_ns: int
    pending: list[ProgramCommand]
    start_mode: str
    start_reason: str

    def swap_drivers(self, prepared: Prepared | None) -> None: ...


def begin(loop: Starting, net: CompiledNet | None) -> None:
    """Decide and prepare the start of `net` (None: no program, nothing to start)."""
    decision = StartDecision("cold", loop.start_reason)
    config = loop.config
    # The supervisor's restart of a crashed scan process continues the PLC as it was: the
    # boot policy is for a start of the machine or of `softplc run` (docs/retain.md).
    policy = "warm" if config.restarts else config.boot_policy
    if config.state_dir is not None:
        store = RetainStore.open(config.state_dir)  # StateDirBusy: another runtime has it
        if store.dir_note:  # in status too (retain.dir_note); said where the operator looks
            print(f"softplc: warning: {store.dir_note}", file=sys.stderr, flush=True)
        decision = decide(store, net, policy)
        loop.retain = RetainWriter(store)
    loop.start_mode, loop.start_reason = decision.mode, decision.reason
    if net is not None and decision.snapshot is not None:
        warm(loop, net, decision.snapshot)
    elif net is not None:
        cold(loop, net, decision)
    if net is not None and policy == "stop" and config.start and decision.ran_before:
        loop.start_reason += "; boot policy stop: not started (resume or start it)"
    if config.paused_at_restart:
        loop.start_reason += (f"; paused at a breakpoint when the scan process died "
                              f"({config.paused_at_restart}): not run on, outputs safe "
                              f"(resume runs on; breakpoints are not retained)")
    continue_count(loop)


def continue_count(loop: Starting) -> None:
    """The scan count never goes back: a scan process started after another one died goes on
    from the count that one last published (the supervisor's snapshot segment outlives it),
    not from the retain snapshot's, up to a retain interval older (issue 26.5). Only the
    count moves: no timer, output or marking depends on it, so a trace still replays."""
    published = loop.writer.published_scan_count() if loop.writer is not None else None
    if published is not None:
        plc = loop.runner.plc
        plc.scan_count = max(plc.scan_count, published + 1)


def cold(loop: Starting, net: CompiledNet, decision: StartDecision | None = None) -> None:
    """Download `net` (and start it, if asked) on the first scan, from its initial marking;
    persistent places and memory symbols from a snapshot of a program of the same name.
    A restart after a crash with no usable snapshot waits STOPPED: nothing says whether the
    program was running, and starting a machine from its initial marking is a person's call."""
    loop.pending = [ProgramCommand(Command.DOWNLOAD, net, id=0)]
    kept = decision.persistent if decision is not None else None
    if kept is not None and (persistent_places(net) or persistent_memory(net.io)):
        _download_keeping(loop, net, kept)
    if _starts_cold(loop.config, net, decision):
        loop.pending.append(ProgramCommand(Command.START, id=0))


def _starts_cold(config: LoopConfig, net: CompiledNet, decision: StartDecision | None) -> bool:
    """`--start` at a cold start, per the boot policy: "stop" acts on it only on a state
    directory that never held a snapshot (a first start); "cold" on the same program only if
    it was RUNNING (an operator's stop is not undone by a restart)."""
    if not config.start or config.restarts:
        return False
    ran_before = decision is None or decision.ran_before
    if config.boot_policy == "stop":
        return not ran_before
    kept = decision.persistent if decision is not None else None
    if config.boot_policy == "cold" and kept is not None \
            and kept.payload["program_hash"] == net.program_hash:
        return bool(kept.payload["state"] == PlcState.RUNNING.name)
    return True


def _download_keeping(loop: Starting, net: CompiledNet, snap: Loaded) -> None:
    """Download `net` now and put in the snapshot's persistent values; a snapshot whose
    values do not fit leaves the initial ones (the queued download), with the reason."""
    plc = loop.runner.plc
    plc.apply(ProgramCommand(Command.DOWNLOAD, net), loop.clock.now_ns())
    try:
        names = restore_persistent(plc, snap.payload)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        loop.runner.plc = Plc.empty(plc.image)
        loop.start_reason += (f"; persistent values of {snap.path.name} unusable "
                              f"({type(exc).__name__}: {exc})")
        return
    loop.pending = []
    loop.swap_drivers(None)  # the program's devices, opened before the first scan
    loop.start_reason += f"; persistent kept from {snap.path.name}: {', '.join(names) or '-'}"


def warm(loop: Starting, net: CompiledNet, snap: Loaded) -> None:
    """Download `net`, open its devices and put the snapshot in; on a snapshot that does
    not fit after all (same hash, unusable content) fall back to a cold start."""
    payload = snap.payload
    config = loop.config
    # A PLC paused at a breakpoint when its scan process died is not run on by the restart:
    # a person was looking at it (docs/debug.md).
    resume = not config.paused_at_restart and (
        config.restarts > 0 or (config.start and config.warm_start == "run"
                                and config.boot_policy == "warm"))
    plc = loop.runner.plc
    plc.apply(ProgramCommand(Command.DOWNLOAD, net), payload["now_ns"])
    try:
        state = restore(plc, payload, resume)
        plants = {name: load_plant(blob)
                  for name, blob in payload.get("field_simulation_only", {}).items()}
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, EOFError) as exc:
        loop.runner.plc = Plc.empty(loop.runner.plc.image)
        cold(loop, net, StartDecision("cold", "", ran_before=True))
        loop.start_mode = "cold"
        loop.start_reason = f"snapshot {snap.path.name} unusable ({type(exc).__name__}: {exc})"
        return
    loop.swap_drivers(None)  # the program's devices, opened before the first scan
    for driver in loop.runner.drivers:
        if driver.name in plants and hasattr(driver, "plant"):
            driver.plant = plants[driver.name]  # simulation only: the field side
    loop.clock = ContinuedClock(loop.clock, payload["now_ns"])
    loop.retained_ns = payload["now_ns"]
    loop.start_reason += f" -> {state.name}"
