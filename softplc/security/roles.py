"""Roles, the acts a request may ask for whichever door it came through, and the one table of
which role each act needs (docs/security.md, "Users, roles and credentials").

Owns: Role (viewer < operator < engineer < admin, each holding the rights of those below),
Act (the lifecycle's commands plus reading, HMI writes and the audit trail), COMMAND_ROLES
(act -> the least role). HTTP routes, OPC UA methods and node writes, the Modbus write policy
and the CLI map onto these acts (api/roles.py, opcua/access.py, hmi/); none keeps a role of
its own.
Does not know: doors, routes, users, credentials.
"""

from __future__ import annotations

import enum
from typing import Final

from softplc.core.lifecycle import Command


class Role(enum.IntEnum):
    """What a user may do; a higher role may do everything a lower one may."""

    VIEWER = 1  # read: status, symbols, events, the program, the page
    OPERATOR = 2  # start, stop, resume, symbol (HMI) writes
    ENGINEER = 3  # download, reset, kill, force and unforce, breakpoints and single scans
    ADMIN = 4  # users, keys, the audit trail

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, text: str) -> Role:
        """A role from its name (`operator`); ValueError naming the choices otherwise."""
        try:
            return cls[text.strip().upper()]
        except KeyError:
            raise ValueError(f"unknown role {text!r}: one of "
                             f"{', '.join(r.label for r in cls)}") from None


class Act(enum.Enum):
    """What a request asks to do. The lifecycle's commands keep their wire names."""

    READ = "read"  # status, symbols, the program, events, history, why, the net
    WRITE = "write"  # an HMI write of a symbol (HTTP PUT, OPC UA Write, Modbus write)
    START = Command.START.value
    STOP = Command.STOP.value
    RESUME = Command.RESUME.value
    DOWNLOAD = Command.DOWNLOAD.value
    RESET = Command.RESET.value
    KILL = Command.KILL.value
    FORCE = Command.FORCE.value
    UNFORCE = Command.UNFORCE.value
    BREAK = Command.BREAK.value
    UNBREAK = Command.UNBREAK.value
    STEP = Command.STEP.value
    CONTINUE = Command.CONTINUE.value
    AUDIT = "audit"  # read the audit trail, or follow it
    ADMINISTER = "administer"  # anything not listed: closed to all but admins

    @classmethod
    def of(cls, command: Command) -> Act:
        return cls(command.value)


_V, _O, _E, _A = Role.VIEWER, Role.OPERATOR, Role.ENGINEER, Role.ADMIN
# act -> the least role, for every door (tests/security/test_doors.py enumerates the doors).
COMMAND_ROLES: Final[dict[Act, Role]] = {
    Act.READ: _V,
    Act.WRITE: _O, Act.START: _O, Act.STOP: _O, Act.RESUME: _O,
    Act.DOWNLOAD: _E, Act.RESET: _E, Act.KILL: _E, Act.FORCE: _E, Act.UNFORCE: _E,
    # Breakpoints and single scans (docs/debug.md): they stop a machine's program mid-way.
    Act.BREAK: _E, Act.UNBREAK: _E, Act.STEP: _E, Act.CONTINUE: _E,
    Act.AUDIT: _A, Act.ADMINISTER: _A,
}


def needs(act: Act) -> Role:
    return COMMAND_ROLES[act]
