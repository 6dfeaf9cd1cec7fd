"""Breakpoints and single scans applied to a PLC (docs/debug.md): the debugging commands, the
cycle of a paused PLC and the check after each round.

Owns: BREAK, UNBREAK, STEP and CONTINUE as the scan applies them (refused by state like the
lifecycle's commands, the state unchanged), what a paused cycle does (inputs latched, forced
inputs shown, no round, no scan counted, the outputs per the pause's policy), and entering a
pause at the end of a scan.
Does not know: the order of a scan (core/scan.py calls these), clocks, processes.
"""

from __future__ import annotations

from collections.abc import Sequence

from softplc.core.breakpoints import BreakRefused, Outputs, Pause, parse_spec
from softplc.core.expr import EvalContext
from softplc.core.held import HeldOutputs
from softplc.core.lifecycle import Command, CommandRejected, PlcState, accepting
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.result import ScanResult
from softplc.core.snapshot import CommandReply

DEBUG_COMMANDS = frozenset({Command.BREAK, Command.UNBREAK, Command.STEP, Command.CONTINUE})
MAX_STEPS = 1_000_000  # scans one step may run


def apply(plc: Plc, cmd: ProgramCommand, now_ns: int) -> str:
    """One debugging command. Raises CommandRejected and changes nothing when refused."""
    try:
        if cmd.command is Command.BREAK:
            return _add(plc, cmd)
        if cmd.command is Command.UNBREAK:
            ident = None if cmd.symbol is None else int(cmd.symbol.removeprefix("b"))
            gone = plc.debug.remove(ident)
            return f"unbreak: removed {', '.join(f'b{b.id}' for b in gone) or 'nothing'}"
    except (BreakRefused, ValueError) as exc:
        raise CommandRejected(plc.state, cmd.command,
                              f"{cmd.command.value} refused: {exc}") from None
    pause = plc.debug.pause
    if plc.state is not PlcState.RUNNING or pause is None:
        where = "not paused" if plc.state is PlcState.RUNNING else "no pause"
        raise CommandRejected(plc.state, cmd.command, (
            f"{cmd.command.value} is not accepted in state {plc.state.name} ({where}) "
            f"(accepted in {accepting(cmd.command)}): set a breakpoint (softplc break add)"))
    if cmd.command is Command.CONTINUE:
        plc.unpause(now_ns)
        return f"continue: running from scan {pause.k + 1} (state RUNNING)"
    steps = cmd.value or 1
    if not 1 <= steps <= MAX_STEPS:
        raise CommandRejected(plc.state, cmd.command,
                              f"step refused: {steps} scans (1..{MAX_STEPS})")
    plc.unpause(now_ns, steps)
    return (f"step: {steps} scan(s) from scan {pause.k + 1}, then paused "
            f"(scan count {pause.k + 1 + steps}; state RUNNING)")


def _add(plc: Plc, cmd: ProgramCommand) -> str:
    if plc.net is None:
        raise BreakRefused(f"no program is loaded (state {plc.state.name}; break is accepted "
                           f"in {accepting(Command.BREAK)})")
    on, target = parse_spec(cmd.symbol or "")
    outputs = Outputs.SAFE if cmd.value == 1 else Outputs.HOLD
    state = plc.engine.state if plc.engine is not None else None
    point = plc.debug.add(on, target, outputs, plc.net, state, plc.context)
    return f"break: {point.describe()} (outputs {outputs.value} while paused)"


def paused_cycle(plc: Plc, now_ns: int, commands: Sequence[ProgramCommand],
                 hmi_count: int, replies: Sequence[CommandReply]) -> ScanResult:
    """A cycle of a paused PLC, after commands, HMI writes and the input latch: no event
    conditions, no round, no scan counted, the previous image kept for the next step's edges;
    the devices get the pause's outputs (`safe`: their safe values, again every cycle)."""
    plc.debug.cycle_ns = now_ns
    if plc.debug.held is not None:
        plc.drive_safe()
    return ScanResult(plc.image, (), (), (), {}, tuple(replies), bool(commands or hmi_count))


def after_round(plc: Plc, ctx: EvalContext, fired: Sequence[int], now_ns: int) -> Pause | None:
    """After scan `plc.scan_count`'s round (not yet counted): the pause it ends in, if any."""
    assert plc.net is not None and plc.engine is not None
    return plc.debug.after_scan(plc.net, plc.engine.state, ctx, fired, plc.scan_count, now_ns)


def enter(plc: Plc, pause: Pause) -> None:
    """At the very end of the scan that pauses (its image already the next edges' previous):
    with `safe`, the program's outputs put aside and the safe values out."""
    if pause.outputs is Outputs.SAFE:
        plc.debug.held = HeldOutputs.of(plc.image)
        plc.drive_safe()
