"""Program lifecycle: PLC states x program commands, as a table (docs/design.md section 4).

Owns: PlcState, Command, the transition table, CommandRejected.
Does not know: what a program is, how a scan runs, where commands come from.
"""

from __future__ import annotations

import enum


class PlcState(enum.IntEnum):
    """Numeric values are part of the Modbus status block: never renumber."""

    EMPTY = 0
    STOPPED = 1
    RUNNING = 2
    KILLED = 3
    FAULTED = 4


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


class CommandRejected(Exception):
    """A command that the current state does not accept. The state is unchanged."""

    def __init__(self, state: PlcState, command: Command, reason: str = "") -> None:
        self.state = state
        self.command = command
        self.reason = reason or (f"{command.value} is not accepted in state {state.name} "
                                 f"(accepted in {accepting(command)})")
        super().__init__(self.reason)


S, C = PlcState, Command

# (state, command) -> next state. Absent pairs are rejected. A download while RUNNING is an
# online change, which the scan handles separately (it needs the old and new nets).
TRANSITIONS: dict[tuple[PlcState, Command], PlcState] = {
    (S.EMPTY, C.DOWNLOAD): S.STOPPED,
    (S.STOPPED, C.DOWNLOAD): S.STOPPED,
    (S.STOPPED, C.START): S.RUNNING,
    (S.STOPPED, C.RESUME): S.RUNNING,
    (S.STOPPED, C.RESET): S.STOPPED,
    (S.STOPPED, C.KILL): S.KILLED,
    (S.RUNNING, C.DOWNLOAD): S.RUNNING,
    (S.RUNNING, C.STOP): S.STOPPED,
    (S.RUNNING, C.KILL): S.KILLED,
    (S.KILLED, C.DOWNLOAD): S.STOPPED,
    (S.KILLED, C.RESET): S.STOPPED,
    (S.FAULTED, C.DOWNLOAD): S.STOPPED,
    (S.FAULTED, C.RESET): S.STOPPED,
    (S.FAULTED, C.KILL): S.KILLED,
}


def next_state(state: PlcState, command: Command) -> PlcState:
    try:
        return TRANSITIONS[(state, command)]
    except KeyError:
        raise CommandRejected(state, command) from None


def accepting(command: Command) -> str:
    """The states that accept `command`, for a refusal's message."""
    if command is Command.UNFORCE:
        return "every state"
    if command is Command.FORCE:  # wherever a program is loaded (core/scan.py)
        return ", ".join(sorted(s.name for s in PlcState if s is not PlcState.EMPTY)) + \
            " (any state with a program loaded)"
    states = sorted({s.name for (s, c) in TRANSITIONS if c is command})
    if command is Command.DOWNLOAD and "RUNNING" not in states:
        states.append("RUNNING (online change)")
    return ", ".join(states) or "no state"
