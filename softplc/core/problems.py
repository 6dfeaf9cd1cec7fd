"""Located problems in a program or symbols file, and the one error that carries them all.

Owns: Problem (file, line, YAML path, message) and ProgramError.
Does not know: how files are read.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True, slots=True, order=True)
class Problem:
    file: str
    line: int
    path: str  # YAML path, e.g. transitions.c1_start.when
    message: str

    def __str__(self) -> str:
        where = f"{self.path}: " if self.path else ""
        return f"{self.file}:{self.line}: {where}{self.message}"


class ProgramError(Exception):
    """Every problem found in a program (validation collects them all before raising)."""

    def __init__(self, problems: Sequence[Problem]) -> None:
        self.problems = tuple(problems)
        super().__init__("\n".join(str(p) for p in self.problems))
