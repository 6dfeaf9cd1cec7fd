"""Located problems in a program or symbols file, and the one error that carries them all.

Owns: Problem (file, line, YAML path, message) and ProgramError; FaultCode and PlcFault,
the contract of a fault raised while a program runs.
Does not know: how files are read.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass

from softplc.core.errors import SoftplcError


@dataclass(frozen=True, slots=True, order=True)
class Problem:
    file: str
    line: int
    path: str  # YAML path, e.g. transitions.c1_start.when
    message: str

    def __str__(self) -> str:
        where = f"{self.path}: " if self.path else ""
        return f"{self.file}:{self.line}: {where}{self.message}"


class ProgramError(SoftplcError):
    """Every problem found in a program (validation collects them all before raising)."""

    def __init__(self, problems: Sequence[Problem]) -> None:
        self.problems = tuple(problems)
        super().__init__("\n".join(str(p) for p in self.problems))


class FaultCode(enum.IntEnum):
    """Why the PLC is FAULTED: the `fault_code` of status, the Modbus status block and retain.
    Values are part of the Modbus map (docs/modbus.md): never renumber, only append."""

    NONE = 0
    WATCHDOG = 1  # one scan ran longer than period x watchdog factor
    DEVICE = 2  # a device stopped answering beyond its fault policy
    PROGRAM = 3  # the running program raised (an action, a guard, the engine, a swap)
    LIMIT = 4  # a resource limit of the running program was exceeded (tokens, work per scan)
    STALL = 5  # a cycle started later than period x watchdog factor (pause, starvation)
    INTERNAL = 6  # any other exception inside a scan (a bug of softplc itself)


class PlcFault(SoftplcError):
    """Raised inside a scan by the program's execution (the engine, a limit) to fault the PLC:
    the scan turns it into FAULTED with safe outputs, `code` and `reason` in status. Any other
    exception inside a scan faults the PLC too, as FaultCode.INTERNAL."""

    def __init__(self, code: FaultCode, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason
