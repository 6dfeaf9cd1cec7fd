"""A trace as a VCD file (IEEE 1364 value change dump) that GTKWave and other waveform
viewers open (issue 32, item 4).

Owns: the VCD text: one scope per program with its symbols (bools as 1-bit wires, integer
types as vectors of their width, reals and scaled symbols as `real` variables holding the value
core/present.py gives them, a scaled symbol's raw count beside it as NAME_raw), a `places`
scope with each place's marking as an integer (subnet instances as nested scopes), the time in
nanoseconds from the trace's first scan, values as they stand after each scan, to the run's end.
Does not know: how the trace is replayed (debug/tracewalk.py), what the values mean.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from softplc.core.datatypes import INFO, SymType
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc
from softplc.core.present import plotted
from softplc.core.symbols import Symbol
from softplc.debug.tracewalk import walk

_FIRST, _LAST = 33, 126  # identifier codes: printable ASCII (IEEE 1364 section 18.2)
_REALS = frozenset({SymType.REAL, SymType.LREAL})
RAW_SUFFIX = "_raw"  # a scaled symbol's raw count, beside its engineering value


@dataclass(frozen=True, slots=True)
class Signal:
    """One VCD variable: its code, kind (wire, integer, real), width and where it lives."""

    code: str
    kind: str
    width: int
    scope: tuple[str, ...]
    name: str


def _code(n: int) -> str:
    base = _LAST - _FIRST + 1
    out = ""
    while True:
        n, digit = divmod(n, base)
        out += chr(_FIRST + digit)
        if n == 0:
            return out
        n -= 1


def signals(net: CompiledNet) -> tuple[list[tuple[Symbol, Signal]], list[Signal]]:
    """The symbols' signals (declaration order; a scaled symbol's raw count right after it)
    and the places' (net order)."""
    syms: list[tuple[Symbol, Signal]] = []
    for sym in net.io.symbols.values():
        bits = INFO[sym.type].bits
        if sym.type is SymType.BOOL:
            syms.append((sym, Signal(_code(len(syms)), "wire", 1, (), sym.name)))
        elif sym.type in _REALS or sym.scaling is not None:
            syms.append((sym, Signal(_code(len(syms)), "real", 64, (), sym.name)))
        if sym.scaling is not None:
            syms.append((sym, Signal(_code(len(syms)), "wire", bits, (), sym.name + RAW_SUFFIX)))
        elif sym.type not in _REALS and sym.type is not SymType.BOOL:
            syms.append((sym, Signal(_code(len(syms)), "wire", bits, (), sym.name)))
    first = len(syms)
    places = [Signal(_code(first + p), "integer", 32, ("places", *name.split(".")[:-1]),
                     name.split(".")[-1]) for p, name in enumerate(net.place_names)]
    return syms, places


def _value(sig: Signal, value: object) -> str:
    if sig.kind == "real":
        return f"r{float(value)!r} {sig.code}"  # type: ignore[arg-type]
    number = int(value)  # type: ignore[call-overload]
    if sig.width == 1:
        return f"{1 if number else 0}{sig.code}"
    return f"b{number & ((1 << sig.width) - 1):b} {sig.code}"


def header(net: CompiledNet, syms: list[Signal], places: list[Signal], first_t: int) -> str:
    lines = ["$version softplc $end",
             f"$comment program {net.name} {net.program_hash[:12]}; time 0 is the trace's "
             f"first scan, t = {first_t} ns{_units(net)} $end",
             "$timescale 1 ns $end", f"$scope module {net.name} $end"]
    lines += [f"$var {s.kind} {s.width} {s.code} {s.name} $end" for s in syms]
    scope: tuple[str, ...] = ()
    for sig in places:
        common = 0
        while common < min(len(scope), len(sig.scope)) and scope[common] == sig.scope[common]:
            common += 1
        lines += ["$upscope $end"] * (len(scope) - common)
        lines += [f"$scope module {part} $end" for part in sig.scope[common:]]
        scope = sig.scope
        lines.append(f"$var {sig.kind} {sig.width} {sig.code} {sig.name} $end")
    lines += ["$upscope $end"] * len(scope)
    lines += ["$upscope $end", "$enddefinitions $end"]
    return "\n".join(lines) + "\n"


def _units(net: CompiledNet) -> str:
    """`; units: level %, temperature °C` for the scaled symbols (VCD has no unit field)."""
    units = [f"{s.name} {s.scaling.unit}" for s in net.io.symbols.values()
             if s.scaling is not None and s.scaling.unit]
    return f"; units: {', '.join(units)}" if units else ""


def _sample(plc: Plc, syms: list[tuple[Symbol, Signal]], places: list[Signal]) -> list[str]:
    marking = plc.engine.state.marking if plc.engine is not None and plc.net is not None \
        else None
    out = [_value(sig, plotted(sym.type.value, raw, sym.scaling) if sig.kind == "real"
                  else raw)
           for sym, sig in syms for raw in (plc.image.get(sym.address),)]
    out += [_value(sig, int(marking[p]) if marking is not None and p < len(marking) else 0)
            for p, sig in enumerate(places)]
    return out


def changes(trace_path: str | Path, net: CompiledNet) -> Iterator[tuple[int, list[str]]]:
    """(the scan's t in ns, the value lines that changed), one per scan."""
    syms, places = signals(net)
    last: dict[str, str] = {}
    for scanned in walk(trace_path, net):
        now = _sample(scanned.plc, syms, places)
        changed = [v for v in now if last.get(_code_of(v)) != v]
        last.update((_code_of(v), v) for v in changed)
        yield int(scanned.record["t"]), changed


def _code_of(line: str) -> str:
    return line.split(" ", 1)[1] if line[0] in "br" else line[1:]


def write_vcd(trace_path: str | Path, net: CompiledNet, out: IO[str]) -> int:
    """Write the trace replayed with `net` as VCD to `out`; returns the scans written. The
    dump ends at the run's end: the last scan's values hold for one period (the time between
    the last two scans). Raises TraceDiverges (a ValueError) when the trace does not replay."""
    syms, places = signals(net)
    scans = first_t = last_t = period = 0
    for t, changed in changes(trace_path, net):
        if scans == 0:
            first_t = t
            out.write(header(net, [s for _, s in syms], places, t))
            out.write("#0\n$dumpvars\n" + "".join(v + "\n" for v in changed) + "$end\n")
        elif changed:
            out.write(f"#{t - first_t}\n" + "".join(v + "\n" for v in changed))
        period = t - last_t if scans else 0
        scans, last_t = scans + 1, t
    if period > 0:
        out.write(f"#{last_t + period - first_t}\n")
    return scans
