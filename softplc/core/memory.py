"""What memory symbols hold when a program is loaded or started: their `init:` values.

Owns: which memory symbols a download, a reset, an online change, a cold or a warm start sets
to its initial value (docs/retain.md, retain per variable), and setting them; which keep a
value across programs (another program's variable of the same name, address, type and scale).
Does not know: when those happen (core/plc.py, runtime/retain/codec.py), YAML, files.
"""

from __future__ import annotations

from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any

from softplc.core.image import ProcessImage
from softplc.core.symbols import Direction, IoImage, Retain, Symbol, unretained_memory


def start_value(sym: Symbol) -> int:
    """The raw bits a memory symbol starts with: its `init:`, else 0."""
    return 0 if sym.init_raw is None else sym.init_raw


def unretained(image: ProcessImage, io: IoImage) -> None:
    """Every `retain: none` memory symbol to its initial value: at every start (warm or
    cold), download and reset."""
    for sym in unretained_memory(io):
        image.set(sym.address, start_value(sym))


def _variable(sym: Symbol) -> Hashable:
    """What makes two declarations one variable: the name, the location, the type and the
    scale (the same raw bits under another name, type or scale would be another value)."""
    scale = (sym.scaling.raw, sym.scaling.eng) if sym.scaling is not None else None
    return sym.name, sym.address, sym.type, scale


def _memory(io: IoImage) -> list[Symbol]:
    return [s for s in io.symbols.values() if s.direction is Direction.MEMORY]


def initialized(image: ProcessImage, io: IoImage, before: IoImage | None,
                same_program: bool = True) -> tuple[str, ...]:
    """The memory symbols of `io` that are new to `image` take their initial value; returns
    the names of those that kept a value across programs (sorted).

    `before` is the io image of the program loaded until now (None when the image holds none,
    as at a cold start); `same_program`: the new program has its name (another version, an
    online change). A variable both declare (the same name, address, type and scale) keeps
    its value. Within a program, a symbol new to it takes its `init:` (without one, what its
    location held); a program of another name starts every other memory symbol at its
    `init:`, 0 without one (a different application starts from its own initial values), and
    keeps only the variables both programs declare alike, not `retain: none` ones: those are
    named, so that a reply, status and the audit trail can say so (docs/retain.md)."""
    known = set() if before is None else {_variable(s) for s in _memory(before)}
    kept: list[str] = []
    for sym in _memory(io):
        if _variable(sym) in known and (same_program or sym.retain is not Retain.NONE):
            if not same_program:
                kept.append(sym.name)
        elif sym.init_raw is not None or (not same_program and before is not None):
            image.set(sym.address, start_value(sym))
    return tuple(sorted(kept))


@dataclass(frozen=True, slots=True)
class Kept:
    """The memory symbols that kept a value from another program at the last download."""

    program: str  # the program they kept it from
    symbols: tuple[str, ...]

    def note(self) -> str:
        """As a download's reply says it (and so the audit record of its request)."""
        return f"; kept values from {self.program}: {', '.join(self.symbols)}" \
            if self.symbols else ""

    def as_dict(self) -> dict[str, Any]:
        return {"from": self.program, "symbols": list(self.symbols)}
