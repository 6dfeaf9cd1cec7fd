"""A trace as a VCD file (IEEE 1364 value change dump) that GTKWave and other waveform
viewers open (issue 32, item 4).

Owns: the VCD text: one scope per program with its symbols (bools as 1-bit wires, words as
16-bit vectors, other numeric types as 32-bit vectors or reals), a `places` scope with each
place's marking as an integer (subnet instances as nested scopes), the time in nanoseconds
from the trace's first scan, values as they stand after each scan.
Does not know: how the trace is replayed (runtime/tracewalk.py), what the values mean.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from softplc.core.net import CompiledNet
from softplc.core.scan import Plc
from softplc.core.symbols import Symbol
from softplc.runtime.tracewalk import walk

_FIRST, _LAST = 33, 126  # identifier codes: printable ASCII (IEEE 1364 section 18.2)
_REAL_TYPES = frozenset({"real", "lreal", "float", "double"})


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
    """The symbols' signals (declaration order) and the places' (net order)."""
    syms = []
    for i, sym in enumerate(net.io.symbols.values()):
        kind = sym.type.value
        if kind == "bool":
            sig = Signal(_code(i), "wire", 1, (), sym.name)
        elif kind in _REAL_TYPES:
            sig = Signal(_code(i), "real", 64, (), sym.name)
        else:
            sig = Signal(_code(i), "wire", 16 if kind == "word" else 32, (), sym.name)
        syms.append((sym, sig))
    first = len(syms)
    places = [Signal(_code(first + p), "integer", 32, ("places", *name.split(".")[:-1]),
                     name.split(".")[-1]) for p, name in enumerate(net.place_names)]
    return syms, places


def _value(sig: Signal, value: object) -> str:
    if sig.kind == "real" or isinstance(value, float):
        return f"r{float(value)!r} {sig.code}"  # type: ignore[arg-type]
    number = int(value)  # type: ignore[call-overload]
    if sig.width == 1:
        return f"{1 if number else 0}{sig.code}"
    return f"b{number & ((1 << sig.width) - 1):b} {sig.code}"


def header(net: CompiledNet, syms: list[Signal], places: list[Signal], first_t: int) -> str:
    lines = ["$version softplc $end",
             f"$comment program {net.name} {net.program_hash[:12]}; time 0 is the trace's "
             f"first scan, t = {first_t} ns $end",
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


def _sample(plc: Plc, syms: list[tuple[Symbol, Signal]], places: list[Signal]) -> list[str]:
    marking = plc.engine.state.marking if plc.engine is not None and plc.net is not None \
        else None
    out = [_value(sig, plc.image.get(sym.address)) for sym, sig in syms]
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
    """Write the trace replayed with `net` as VCD to `out`; returns the scans written.
    Raises TraceDiverges (a ValueError) when the trace does not replay with `net`."""
    syms, places = signals(net)
    scans = first_t = 0
    for t, changed in changes(trace_path, net):
        if scans == 0:
            first_t = t
            out.write(header(net, [s for _, s in syms], places, t))
            out.write("#0\n$dumpvars\n" + "".join(v + "\n" for v in changed) + "$end\n")
        elif changed:
            out.write(f"#{t - first_t}\n" + "".join(v + "\n" for v in changed))
        scans += 1
    return scans
