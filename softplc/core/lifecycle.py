"""Program lifecycle: PLC states x program commands, as a table (docs/design.md section 4).

Owns: PlcState (the public state: status, Modbus, API), Stage (the lifecycle's own state:
PlcState with STOPPED split into READY and SUSPENDED), Command, the transition table,
CommandRejected and the wording of refusals.
Does not know: what a program is, how a scan runs, where commands come from.
"""

from __future__ import annotations

import enum

from softplc.core.errors import SoftplcError

TYPE_CHECKING = False  # typing costs a client command's start (issue 40)
if TYPE_CHECKING:
    from typing import Final


class PlcState(enum.IntEnum):
    """Numeric values are part of the Modbus status block: never renumber."""

    EMPTY = 0
    STOPPED = 1
    RUNNING = 2
    KILLED = 3
    FAULTED = 4


class Stage(enum.Enum):
    """What the table decides on. STOPPED is two stages, because `start` would throw away a
    marking that stands for real parts (issue 29): READY holds the initial marking (after a
    download or a reset: `start` runs it), SUSPENDED the marking a `stop` froze while RUNNING
    (`resume` continues it; `reset` then `start` begins again). OPC UA Part 10's Ready and
    Suspended are these two."""

    EMPTY = (PlcState.EMPTY, "")
    READY = (PlcState.STOPPED, "ready: initial marking")
    SUSPENDED = (PlcState.STOPPED, "stopped while running: marking kept")
    RUNNING = (PlcState.RUNNING, "")
    KILLED = (PlcState.KILLED, "")
    FAULTED = (PlcState.FAULTED, "")

    @property
    def state(self) -> PlcState:
        return self.value[0]

    @property
    def label(self) -> str:
        """The state as people read it: `STOPPED (ready: initial marking)`."""
        return f"{self.state.name} ({self.value[1]})" if self.value[1] else self.state.name


def stage_of(state: PlcState, marking_kept: bool) -> Stage:
    """The stage of a PLC in `state`; `marking_kept`: a stop froze its marking (STOPPED only)."""
    if state is PlcState.STOPPED:
        return Stage.SUSPENDED if marking_kept else Stage.READY
    return _PLAIN[state]


class Command(enum.Enum):
    DOWNLOAD = "download"
    START = "start"
    STOP = "stop"
    RESUME = "resume"
    RESET = "reset"
    KILL = "kill"
    # Forcing (docs/design.md section 10): not in the table below, never changes the state. FORCE
    # is accepted wherever a program is loaded, UNFORCE in every state (core/scan.py).
    FORCE = "force"
    UNFORCE = "unforce"
    # Debugging (docs/debug.md): not in the table either; the state stays RUNNING. BREAK is
    # accepted wherever a program is loaded, UNBREAK in every state, STEP and CONTINUE while
    # paused at a breakpoint (core/pausing.py).
    BREAK = "break"
    UNBREAK = "unbreak"
    STEP = "step"
    CONTINUE = "continue"


# The commands the table below does not decide: they never change the state.
OUTSIDE_TABLE: Final = frozenset({Command.FORCE, Command.UNFORCE, Command.BREAK,
                                  Command.UNBREAK, Command.STEP, Command.CONTINUE})


class CommandRejected(SoftplcError):
    """A command that the current state does not accept. The state is unchanged."""

    def __init__(self, state: PlcState, command: Command, reason: str = "") -> None:
        self.state = state
        self.command = command
        self.reason = reason or (f"{command.value} is not accepted in state {state.name} "
                                 f"(accepted in {accepting(command)})")
        super().__init__(self.reason)


S, C = Stage, Command
_PLAIN: Final = {s.state: s for s in Stage if s.state is not PlcState.STOPPED}

# (stage, command) -> next stage. Absent pairs are rejected. A download while RUNNING is an
# online change, which the scan handles separately (it needs the old and new nets).
TRANSITIONS: dict[tuple[Stage, Command], Stage] = {
    (S.EMPTY, C.DOWNLOAD): S.READY,
    (S.READY, C.DOWNLOAD): S.READY,
    (S.READY, C.START): S.RUNNING,
    (S.READY, C.RESET): S.READY,
    (S.READY, C.KILL): S.KILLED,
    (S.SUSPENDED, C.DOWNLOAD): S.READY,
    (S.SUSPENDED, C.RESUME): S.RUNNING,
    (S.SUSPENDED, C.RESET): S.READY,
    (S.SUSPENDED, C.KILL): S.KILLED,
    (S.RUNNING, C.DOWNLOAD): S.RUNNING,
    (S.RUNNING, C.STOP): S.SUSPENDED,
    (S.RUNNING, C.KILL): S.KILLED,
    (S.KILLED, C.DOWNLOAD): S.READY,
    (S.KILLED, C.RESET): S.READY,
    (S.FAULTED, C.DOWNLOAD): S.READY,
    (S.FAULTED, C.RESET): S.READY,
    (S.FAULTED, C.KILL): S.KILLED,
}

# What would work instead, for the refusals people meet after a stop or a download.
_HINTS: Final = {
    (S.SUSPENDED, C.START): "start would throw the kept marking away: `resume` continues "
                            "from it, or `reset` then `start` runs from the initial marking",
    (S.READY, C.RESUME): "nothing to resume: the marking is the initial one; `start` runs it",
}


def next_stage(stage: Stage, command: Command) -> Stage:
    try:
        return TRANSITIONS[(stage, command)]
    except KeyError:
        raise CommandRejected(stage.state, command, refusal(stage, command)) from None


def next_state(state: PlcState, command: Command, marking_kept: bool = False) -> PlcState:
    return next_stage(stage_of(state, marking_kept), command).state


def refusal(stage: Stage, command: Command) -> str:
    """Why `command` is refused in `stage`, the stages that would take it, and what works."""
    hint = _HINTS.get((stage, command))
    return (f"{command.value} is not accepted in state {stage.label} (accepted in "
            f"{accepting(command)})" + (f": {hint}" if hint else ""))


def accepting(command: Command) -> str:
    """The states that accept `command`, for a refusal's message (both STOPPED stages: STOPPED)."""
    if command is Command.UNFORCE or command is Command.UNBREAK:
        return "every state"
    if command is Command.STEP or command is Command.CONTINUE:
        return "RUNNING (paused at a breakpoint)"
    if command is Command.FORCE or command is Command.BREAK:  # wherever a program is loaded
        return ", ".join(sorted(s.name for s in PlcState if s is not PlcState.EMPTY)) + \
            " (any state with a program loaded)"
    stages = {s for (s, c) in TRANSITIONS if c is command}
    if {S.READY, S.SUSPENDED} <= stages:
        stages -= {S.READY, S.SUSPENDED}
        names = [PlcState.STOPPED.name]
    else:
        names = []
    return ", ".join(sorted(names + [s.label for s in stages])) or "no state"
