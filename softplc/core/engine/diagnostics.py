"""Run-time errors of a program's expressions, kept as located messages.

Owns: the first MAX_DIAGNOSTICS messages (file:line and scan in front), the count of all of
them, the scan being run, and guard evaluation (a guard that raises is false and reported).
Does not know: the marking, enabling, firing.
"""

from __future__ import annotations

from softplc.core.expr import Compiled, EvalContext
from softplc.core.net import CompiledNet

MAX_DIAGNOSTICS = 100


class Diagnostics:
    """Never silent, never a crash: what failed, where, in which scan."""

    __slots__ = ("count", "messages", "net", "scan")

    def __init__(self, net: CompiledNet) -> None:
        self.net = net
        self.messages: list[str] = []  # the first MAX_DIAGNOSTICS, located
        self.count = 0  # every one, also past the list's cap
        self.scan = 0  # the scan being run, for messages (the scan sets it)

    def guard(self, guard: Compiled | None, ctx: EvalContext, where: str) -> bool:
        if guard is None:
            return True
        try:
            return bool(guard(ctx))
        except (KeyError, TypeError, ValueError, ArithmeticError) as exc:
            self.report(f"{where}: guard {guard.text!r} failed ({exc}); taken as false")
            return False

    def report(self, message: str) -> None:
        """A run-time error of a guard, an action or a token field. `message` starts with the
        transition's name; the file:line and the scan go in front."""
        self.count += 1
        if len(self.messages) < MAX_DIAGNOSTICS:
            name = message.partition(":")[0]
            where = ""
            for t in self.net.transitions:
                if t.name == name:
                    file, line = (self.net.transition_where[t.index]
                                  if t.index < len(self.net.transition_where) else ("", t.line))
                    where = f"{file}:{line}: " if file else ""
                    break
            self.messages.append(f"scan {self.scan}: {where}transition {message}")
