"""The PLC: one scan as a function of (state, input image, now_ns, commands).

Owns: the order of a scan (docs/design.md section 1) as named phases, each writing the Plc
fields it owns: judge what the runtime observed; apply commands and HMI writes at the scan
boundary; latch inputs; the start-up gate (no round before every device's first input image);
evaluate event conditions; fire one round when RUNNING; outputs (safe values unless RUNNING);
publish the result. A scan that raises faults the PLC instead.
Does not know: clocks, processes, sockets, YAML (programs arrive compiled).

The PLC's memory and program handling (lifecycle, online change, frozen timers) live in
core/plc.py, the judging of the runtime's measurements in core/judge.py, the round itself in
core/engine (fire_round); import their names from there.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import NamedTuple

import numpy as np

from softplc.core import events as event_conditions
from softplc.core import nonfinite, pausing
from softplc.core.breakpoints import Pause
from softplc.core.context import ScanContext
from softplc.core.datatypes import raw_of
from softplc.core.image import AREAS, Area, ProcessImage
from softplc.core.judge import NOTHING_OBSERVED, Observed, judge
from softplc.core.lifecycle import Command, CommandRejected, PlcState
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.problems import FaultCode, PlcFault
from softplc.core.result import ScanResult
from softplc.core.snapshot import CommandReply, HmiWrite, Refusal
from softplc.core.symbols import FIRST_SCAN, scalings

__all__ = ["scan"]



def scan(plc: Plc, inputs: ProcessImage, now_ns: int,
         commands: Sequence[ProgramCommand] = (), hmi: Sequence[HmiWrite] = (),
         observed: Observed = NOTHING_OBSERVED) -> ScanResult:
    """One scan. `plc` is advanced in place and must not be used by anyone else meanwhile;
    `inputs` is only read (its %I areas are latched).

    `observed` is what the runtime measured (device answers, an overrun, a stall): the scan
    judges it before the program runs, per the fault policies (docs/design.md section 8).
    Nothing raised inside a scan escapes it: PlcFault (a limit, a program error) and any
    other exception (a bug) fault the PLC with safe outputs and the reason, and the scan
    returns as a scan of a FAULTED PLC would: faults, not deaths."""
    judged = judge(plc, observed, now_ns)
    replies = _apply_commands(plc, commands, now_ns)
    killed = bool(commands) and any(c.command is Command.KILL and r.ok
                                    for c, r in zip(commands, replies, strict=True))
    try:
        result = _scan_body(plc, inputs, now_ns, commands, hmi, replies, killed,
                            observed.answering)
    except PlcFault as exc:
        result = _faulted(plc, inputs, now_ns, replies, exc.code, exc.reason)
    except Exception as exc:  # a bug of softplc or of a program path we did not foresee
        reason = f"internal error in the scan: {type(exc).__name__}: {exc}"
        result = _faulted(plc, inputs, now_ns, replies, FaultCode.INTERNAL, reason)
    after = plc.devices.after_scan(plc, now_ns) if observed.answering else []
    if judged or after:
        events = (*judged, *result.events, *after)
        result = ScanResult(result.outputs, events, result.fired, result.completed,
                            result.marking_changes, result.replies, True)
    return result



def _apply_commands(plc: Plc, commands: Sequence[ProgramCommand],
                    now_ns: int) -> list[CommandReply]:
    replies = []
    for cmd in commands:
        try:
            message = (pausing.apply(plc, cmd, now_ns) if cmd.command in pausing.DEBUG_COMMANDS
                       else plc.apply(cmd, now_ns)) + plc.debug.noted()
            replies.append(CommandReply(cmd.id, True, message, plc.state))
        except CommandRejected as exc:
            replies.append(CommandReply(cmd.id, False, exc.reason, plc.state,
                                        refusal=Refusal.STATE))
        except Exception as exc:  # a swap that failed half-way: the PLC must not go on with it
            reason = f"{cmd.command.value} failed: {type(exc).__name__}: {exc}"
            plc.fault(FaultCode.INTERNAL, None, reason)
            replies.append(CommandReply(cmd.id, False, reason, plc.state,
                                        refusal=Refusal.STATE))
    return replies


def _faulted(plc: Plc, inputs: ProcessImage, now_ns: int, replies: list[CommandReply],
             code: FaultCode, reason: str) -> ScanResult:
    """The end of a scan whose execution raised: FAULTED (from any state that runs a program),
    outputs safe, inputs latched, the scan counted."""
    if plc.state is PlcState.RUNNING or plc.state is PlcState.STOPPED:
        plc.fault(code, now_ns if plc.state is PlcState.RUNNING else None, reason)
    plc.drive_safe()
    plc.last_events = plc.true_last = frozenset()
    plc.image.latch_inputs(inputs)
    plc.forces.apply_inputs(plc.image)  # forced inputs show in every state
    if plc.engine is not None:
        plc.engine.invalidate()  # a round that raised half-way leaves no cached enabling
    plc.image.copy_into(plc.prev)
    plc.scan_count += 1
    return ScanResult(plc.image, (f"plc_fault:{code.name.lower()}",), (), (), {},
                      tuple(replies), True)


def _scan_body(plc: Plc, inputs: ProcessImage, now_ns: int,
               commands: Sequence[ProgramCommand], hmi: Sequence[HmiWrite],
               replies: list[CommandReply], killed: bool,
               answering: Mapping[str, bool]) -> ScanResult:
    """The order of a scan after its commands (docs/design.md section 1), one phase a line;
    each phase writes the Plc fields it owns."""
    _apply_hmi(plc, hmi, killed)
    _latch_inputs(plc, inputs)
    if plc.debug.paused and plc.state is PlcState.RUNNING:  # at a breakpoint (docs/debug.md)
        return pausing.paused_cycle(plc, now_ns, commands, len(hmi), replies)
    running = plc.state is PlcState.RUNNING and plc.engine is not None and plc.net is not None
    arrived = nonfinite.arrived(plc.image, plc.prev, plc.net.io.symbols) if plc.net else ()
    waiting = _startup_gate(plc, running, answering, now_ns)
    occurred = _conditions(plc, running) if not waiting else ()
    done = _fire(plc, now_ns, occurred) if running and not waiting else _no_round(plc, occurred)
    if arrived:  # a device input's NaN or infinity, said on arrival (core/nonfinite.py)
        done = done._replace(occurred=(*arrived, *done.occurred))
    outputs_changed = _outputs(plc, done, bool(commands or hmi))
    return _publish(plc, done, replies, outputs_changed)


class _Round(NamedTuple):
    """What a scan's firing phase did, for the outputs and publish phases."""

    occurred: tuple[str, ...]  # events: the conditions' and the round's emitted ones
    fired: tuple[str, ...] = ()
    completed: tuple[str, ...] = ()
    changes: dict[str, int] | None = None  # place -> tokens, of the places that changed
    pause: Pause | None = None  # a breakpoint hit or a step ended: pause after it
    ran: bool = True  # a firing round ran (False: outputs safe)


def _apply_hmi(plc: Plc, hmi: Sequence[HmiWrite], killed: bool) -> None:
    """HMI writes at the scan boundary (writes: image), none after a kill."""
    if hmi and not killed:
        plc.apply_hmi(hmi)
        if plc.engine is not None and any(w.address.area is not Area.INPUT for w in hmi):
            plc.engine.refresh_outputs()  # a program-driven output stays the program's


def _latch_inputs(plc: Plc, inputs: ProcessImage) -> None:
    """The input image latched for the whole scan (writes: image's inputs)."""
    plc.image.latch_inputs(inputs)
    plc.forces.apply_inputs(plc.image)  # forcing: a forced input replaces the driver's value


def _startup_gate(plc: Plc, running: bool, answering: Mapping[str, bool],
                  now_ns: int) -> tuple[str, ...]:
    """The start-up gate (issue 26): a device whose first input image has not arrived left
    zeros in the image, not values; nothing may act on them, event conditions included.
    Writes: waiting_io, io_wait. Returns the devices waited for."""
    waiting = plc.waiting_io = plc.awaited(answering)
    if waiting and running:
        plc.wait_for_io(now_ns)
    elif plc.io_wait is not None:
        plc.end_io_wait(now_ns)
    return waiting


def _conditions(plc: Plc, running: bool) -> tuple[str, ...]:
    """The event conditions that occurred this scan (writes: events)."""
    if plc.net is None:
        return ()
    if running and plc.first_round:
        plc.events.rearm()  # a threshold already past at a start is an event
    return event_conditions.evaluate(plc.net.io.events.values(), plc.net.io.symbols,
                                     plc.image, plc.events)


def _fire(plc: Plc, now_ns: int, occurred: tuple[str, ...]) -> _Round:
    """One firing round of a RUNNING PLC and its writes into the image. Writes: first_round,
    context, written_last, last_events, true_last, the image's program outputs."""
    assert plc.engine is not None and plc.net is not None
    # The steady scan allocates no sets: empty ones are shared (issue 15.5).
    now_events = (frozenset(occurred) | plc.last_events if occurred or plc.last_events
                  else _NO_EVENTS)
    if plc.first_round:  # IEC's first-scan flag, read like an event (docs/programs.md)
        now_events, plc.first_round = now_events | _FIRST_SCAN, False
    plc.forces.unapply_outputs(plc.image)  # forcing: the program sees its own values
    ctx = plc.context
    if (ctx is None or ctx.image is not plc.image or ctx.prev is not plc.prev
            or ctx.locations is not plc.locations):
        ctx = plc.context = ScanContext(plc.image, plc.prev, plc.locations, now_events,
                                        plc.typed, scalings(plc.net.io))
    ctx.events = now_events  # one context per image and program, not one per scan
    # Symbols the program wrote last scan count as changed too: the end-of-scan image
    # already holds them, so the image difference alone would miss them.
    changed = _changed(plc)
    for more in (now_events, plc.true_last, plc.written_last):
        if more:
            changed |= more
    before = plc.engine.state.marking.copy()
    plc.engine.scan = plc.scan_count  # diagnostics name the scan
    step = plc.engine.fire_round(ctx, now_ns, changed)
    if step.writes:
        _write(plc, step.writes)
        plc.written_last = {symbol for symbol, _ in step.writes}
    elif plc.written_last:
        plc.written_last = set()
    plc.forces.apply_outputs(plc.image)  # forcing: after Moore/Mealy, before the drivers
    names = plc.net.transitions
    fired = tuple(names[t].name for t in step.fired) if step.fired else ()
    completed = tuple(names[t].name for t in step.completed) if step.completed else ()
    changes = None
    if step.changed_places:
        after = plc.engine.state.marking
        changes = {plc.net.place_names[p]: int(after[p])
                   for p in sorted(step.changed_places) if after[p] != before[p]}
    if ctx.unusable or ctx.reported:  # a NaN or an infinity was read: said once
        occurred = occurred + nonfinite.said(ctx, plc.net.io.symbols)
    emitted = step.emitted
    plc.last_events = frozenset(emitted) if emitted else _NO_EVENTS
    plc.true_last = now_events
    if emitted:
        occurred = occurred + emitted
    pause = None
    if plc.debug.armed and (pause := pausing.after_round(plc, ctx, step.fired, now_ns)):
        occurred = (*occurred, *(f"paused:b{b.id}" for b in pause.hit or ()),
                    *(() if pause.hit else ("paused:step",)))
    if not (occurred or fired or completed or changes or pause):
        return _QUIET_ROUND
    return _Round(occurred, fired, completed, changes, pause)


def _no_round(plc: Plc, occurred: tuple[str, ...]) -> _Round:
    """No firing round (not RUNNING, or waiting for devices): no events carry over."""
    plc.last_events = plc.true_last = frozenset()
    return _Round(occurred, ran=False) if occurred else _NOT_RUN


def _outputs(plc: Plc, done: _Round, commanded: bool) -> bool:
    """The output image: safe values without a round; kept as the previous image for the
    next scan's edges (writes: image, prev). Returns whether the outputs may have changed."""
    if not done.ran:
        plc.drive_safe()
    outputs_changed = (commanded or bool(done.fired or done.completed or done.pause)
                       or plc.state is not PlcState.RUNNING
                       or not _same_outputs(plc.image, plc.prev))
    plc.image.copy_into(plc.prev)
    return outputs_changed


def _publish(plc: Plc, done: _Round, replies: list[CommandReply],
             outputs_changed: bool) -> ScanResult:
    """The scan counted and its result (writes: scan_count, quiet_result, a pause)."""
    plc.scan_count += 1
    if done.pause is not None:
        pausing.enter(plc, done.pause)  # after the copy: the next step's edges see its outputs
    if (done.occurred or done.fired or done.completed or done.changes or replies
            or outputs_changed):
        return ScanResult(plc.image, done.occurred, done.fired, done.completed,
                          done.changes or {}, tuple(replies), outputs_changed)
    quiet = plc.quiet_result  # a scan in which nothing happened: most are such
    if quiet is None or quiet.outputs is not plc.image:
        quiet = plc.quiet_result = ScanResult(plc.image, (), (), (), {}, (), False)
    return quiet


def _changed(plc: Plc) -> set[str]:
    """The symbols whose location differs from the previous scan's image."""
    changed: set[str] = set()
    image, prev = plc.image, plc.prev
    if (image.buf is not None and prev.buf is not None
            and image.buf.tobytes() == prev.buf.tobytes()):
        return changed  # the common scan: one comparison of the whole image
    for area in AREAS:
        now, before = getattr(image, area), getattr(prev, area)
        if now.tobytes() == before.tobytes():
            continue
        for index in np.flatnonzero(now != before).tolist():
            changed.update(plc.by_location.get((area, index), ()))
    return changed


def _write(plc: Plc, writes: Iterable[tuple[str, int | float]]) -> None:
    """The firing round's writes into the image; values already checked against their
    symbol's type (core/engine/outputs.py)."""
    for symbol, value in writes:
        area, index = plc.locations[symbol]
        arr, typed = getattr(plc.image, area), plc.typed.get(symbol)
        arr[index] = (bool(value) if area.endswith("x") else int(value) & 0xFFFF
                      if typed is None else raw_of(typed, value))


def _same_outputs(a: ProcessImage, b: ProcessImage) -> bool:
    return a.outputs_bytes() == b.outputs_bytes()  # one memcmp of the contiguous tail


_NO_EVENTS: frozenset[str] = frozenset()
_QUIET_ROUND = _Round(())  # a round in which nothing happened, shared
_NOT_RUN = _Round((), ran=False)
_FIRST_SCAN: frozenset[str] = frozenset({FIRST_SCAN})
