"""NaN and infinities in `real`/`lreal` symbols: refused where they could come in, said where
they are read (issue 39 item 4).

Owns: the rule and its words. A NaN or an infinity is not a value of the language
(core/values.py): a program's own write never stores one (core/datatypes.py `stored`), and
neither does a typed write at any door (HTTP, OPC UA, force, sim scripts, the debugger: they
all go through core/present.py `accepted`). Two ways remain for the bits of one to reach a
symbol: a Modbus register write (raw bits, hmi/map.py refuses it with exception 03 unless the
symbol says `finite: false`) and a device input (the device's value: it cannot be refused).
A device input's is said on arrival: `arrived`, once a scan after the inputs latch, makes the
event `not_finite:SYMBOL:device:DRIVER` when a real/lreal input's latched value is not finite
and was finite the scan before (the previous image), whether a guard reads it or not.
A guard or an action that reads one reads it as IEEE 754 says (every comparison with NaN is
false: a backstop `or high_switch` still works), and the scan says any other symbol's once,
as the event `not_finite:SYMBOL:modbus` (core/context.py notes the read, `said` makes the
event), and live `why` shows the door beside the value (core/whyguard.py).
Does not know: the net, the scan, the doors' protocols.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from softplc.core.context import ScanContext
from softplc.core.datatypes import INFO, SymType, value_of
from softplc.core.image import ProcessImage
from softplc.core.symbols import Direction, Symbol


def named(value: float) -> str:
    """NaN, +inf or -inf, as a refusal or a diagnostic names it."""
    if math.isnan(value):
        return "NaN"
    return "+inf" if value > 0 else "-inf"


def refusal(name: str, t: SymType, raw: int) -> str | None:
    """Why a raw-bits write of `raw` to the finite symbol `name` of type `t` is refused (a
    NaN or an infinity), None when it is not."""
    if not INFO[t].is_float:
        return None
    value = value_of(t, raw)
    if math.isfinite(value):
        return None
    return (f"symbol {name} is a {t.value}: the value must be a finite number, not "
            f"{named(float(value))} (finite: false in its symbols file lets one in)")


def door(sym: Symbol) -> str:
    """The door the bits of a non-finite value of `sym` came through, in a few words."""
    if sym.direction is Direction.IN:
        return f"a device input (driver {sym.driver})" if sym.driver else "a device input"
    return "a Modbus register write (the one door that writes a real's raw bits)"


def door_word(sym: Symbol) -> str:
    """`door` as one word of an event name: modbus, or device:DRIVER."""
    if sym.direction is Direction.IN:
        return f"device:{sym.driver}" if sym.driver else "device"
    return "modbus"


def said(ctx: ScanContext, symbols: Mapping[str, Symbol]) -> tuple[str, ...]:
    """The events of this scan's round: `not_finite:SYMBOL:DOOR` for each symbol a guard or
    an action read as NaN or an infinity that was not already said; a symbol is said again
    once it has held a finite value in between. Clears the round's notes."""
    for name in [n for n in ctx.reported if n not in ctx.unusable]:
        if name not in symbols or _finite_now(ctx, name):
            ctx.reported.discard(name)
    fresh = sorted(n for n in ctx.unusable - ctx.reported
                   if n in symbols and symbols[n].direction is not Direction.IN)  # `arrived`
    ctx.reported |= ctx.unusable
    ctx.unusable.clear()
    return tuple(f"not_finite:{name}:{door_word(symbols[name])}" for name in fresh)


def _finite_now(ctx: ScanContext, name: str) -> bool:
    area, index = ctx.locations[name]
    t = ctx.typed.get(name)
    return t is None or math.isfinite(value_of(t, int(getattr(ctx.image, area)[index])))


class _Watch:
    """The real and lreal input symbols of one io image, by area: the exponent mask of the
    area's width (all ones: a NaN or an infinity), their indices, the symbols."""

    __slots__ = ("areas", "symbols")

    def __init__(self, symbols: Mapping[str, Symbol]) -> None:
        self.symbols = symbols
        found: dict[str, list[Symbol]] = {}
        for sym in symbols.values():
            if sym.direction is Direction.IN and INFO[sym.type].is_float:
                found.setdefault(sym.address.attr, []).append(sym)
        self.areas = tuple((attr, _EXPONENT[attr], tuple(s.address.index for s in syms),
                            np.array([s.address.index for s in syms], dtype=np.intp),
                            tuple(syms)) for attr, syms in sorted(found.items()))


_EXPONENT = {"id": 0x7F80_0000, "il": 0x7FF0_0000_0000_0000}  # IEEE 754 single, double
_FEW = 24  # up to this many in an area, one test each beats numpy's fixed cost (~1 us a call)
_WATCHES: list[_Watch] = []  # the last few io images' (a process runs one or two at a time)


def arrived(image: ProcessImage, prev: ProcessImage,
            symbols: Mapping[str, Symbol]) -> tuple[str, ...]:
    """`not_finite:SYMBOL:device:DRIVER` for each real/lreal input whose latched value in
    `image` is a NaN or an infinity and whose value in `prev` (the scan before) was finite.
    Measured here (min of 7): 0.2 us a scan without real inputs, 0.6 us with two, 3.7 us
    with 100 in one area (one vectorised test per area with more than _FEW of them)."""
    watch = _WATCHES[0] if _WATCHES and _WATCHES[0].symbols is symbols else None
    if watch is None:
        watch = next((w for w in _WATCHES if w.symbols is symbols), None) or _Watch(symbols)
        _WATCHES[:] = [watch, *(w for w in _WATCHES[:3] if w is not watch)]
    if not watch.areas:
        return ()
    out: tuple[str, ...] = ()
    for attr, mask, indices, at, syms in watch.areas:
        now = getattr(image, attr)
        if len(indices) > _FEW and not ((now[at] & mask) == mask).any():
            continue
        for k, i in enumerate(indices):  # a plain loop: the all-finite scan allocates nothing
            if now.item(i) & mask == mask and getattr(prev, attr).item(i) & mask != mask:
                out += (f"not_finite:{syms[k].name}:{door_word(syms[k])}",)
    return out
