"""What memory symbols hold when a program is loaded or started: their `init:` values.

Owns: which memory symbols a download, a reset, an online change, a cold or a warm start sets
to its initial value (docs/retain.md, retain per variable), and setting them.
Does not know: when those happen (core/plc.py, runtime/retain_codec.py), YAML, files.
"""

from __future__ import annotations

from collections.abc import Hashable

from softplc.core.image import ProcessImage
from softplc.core.symbols import Direction, IoImage, Symbol, unretained_memory


def start_value(sym: Symbol) -> int:
    """The raw bits a memory symbol starts with: its `init:`, else 0."""
    return 0 if sym.init_raw is None else sym.init_raw


def unretained(image: ProcessImage, io: IoImage) -> None:
    """Every `retain: none` memory symbol to its initial value: at every start (warm or
    cold), download and reset."""
    for sym in unretained_memory(io):
        image.set(sym.address, start_value(sym))


def _variable(sym: Symbol) -> Hashable:
    """What makes two declarations one variable: the location, the type and the scale (the
    same raw bits under another type or scale would be another value)."""
    scale = (sym.scaling.raw, sym.scaling.eng) if sym.scaling is not None else None
    return sym.address, sym.type, scale


def initialized(image: ProcessImage, io: IoImage, before: IoImage | None) -> None:
    """The memory symbols with `init:` that are new to `image` take it: those `before` (the
    io image of the program loaded until now; None when the image holds none, as at a cold
    start) did not declare as the same variable. A variable both declare keeps its value, as
    every location of the image does at a download or an online change."""
    known = set() if before is None else {
        _variable(s) for s in before.symbols.values() if s.direction is Direction.MEMORY}
    for sym in io.symbols.values():
        if sym.init_raw is not None and _variable(sym) not in known:
            image.set(sym.address, sym.init_raw)
