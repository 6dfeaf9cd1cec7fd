"""Replay a trace: feed the recorded inputs, commands and HMI writes back into a fresh PLC
and compare every scan's output image bit for bit.

Owns: the reconstruction of each scan's inputs from the trace and the first divergence.
Does not know: devices (replay needs none), clocks (recorded times are used).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softplc.core.image import ProcessImage, parse_address
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.present import raw_text
from softplc.core.scan import scan
from softplc.core.snapshot import HmiWrite
from softplc.runtime.runner import observed_from
from softplc.runtime.trace import image_digest, read_trace


@dataclass(frozen=True, slots=True)
class ReplayResult:
    scans: int
    divergence: str | None  # None: every scan matched

    @property
    def ok(self) -> bool:
        return self.divergence is None


def trace_commands(record: dict[str, Any], net: CompiledNet
                   ) -> tuple[list[ProgramCommand], str]:
    """The commands one scan's record applied (a download: `net` again), and a note when the
    trace ran another program than `net`."""
    commands, note = [], ""
    for entry in record.get("cmd", []):
        command = Command(entry["c"])
        if command is Command.DOWNLOAD:
            if entry.get("hash") and entry["hash"] != net.program_hash:
                note = (f" (the trace ran program {entry.get('program')} "
                        f"{entry['hash'][:12]}, replay runs {net.name} {net.program_hash[:12]})")
            commands.append(ProgramCommand(command, net, bool(entry.get("online"))))
        else:
            commands.append(ProgramCommand(command, symbol=entry.get("symbol"),
                                           value=int(entry.get("value", 0))))
    return commands, note


def apply_inputs(image: ProcessImage, changes: dict[str, dict[str, int]]) -> None:
    """One scan record's input changes ({area: {index: value}}) into `image`."""
    for area, values in changes.items():
        arr = getattr(image, area)
        for index, value in values.items():
            arr[int(index)] = value


def replay(trace_path: str | Path, net: CompiledNet) -> ReplayResult:
    plc = Plc.empty(ProcessImage(net.io.sizes))
    inputs = ProcessImage(net.io.sizes)
    note = ""
    count = 0
    drivers = list(net.io.drivers)
    recorded: dict[str, int] = {}  # output symbols as the trace gave them ("q"; newer traces)
    for count, record in enumerate(read_trace(trace_path), 1):
        recorded.update(record.get("q") or {})
        apply_inputs(inputs, record.get("in", {}))
        commands, why = trace_commands(record, net)
        note = note or why
        hmi = [HmiWrite(parse_address(a), tuple(v)) for a, v in record.get("hmi", [])]
        # Device answers, watchdog overruns and stalls were judged by the scan: fed back, the
        # replay reproduces every fault they caused.
        observed = observed_from(record.get("obs", {}), drivers)
        result = scan(plc, inputs, int(record["t"]), commands, hmi, observed)
        fired = list(result.fired)
        differs = image_digest(result.outputs) != record["out"]
        if differs or fired != record.get("fired", []):
            return ReplayResult(count, (
                f"scan {record['k']} (t={record['t'] / 1e9:.3f} s): "
                f"recorded fired {record.get('fired', [])}, replay fired {fired}; "
                f"output image {_difference(net, recorded, result.outputs) if differs else 'same'}"
                f"{note}"))
    return ReplayResult(count, None)


def _difference(net: CompiledNet, recorded: dict[str, int], outputs: ProcessImage) -> str:
    """The first differing output symbols with both values (a trace without "q", written
    before it existed, only says that the image differs)."""
    diffs = []
    for symbol in net.io.symbols.values():
        if symbol.name in recorded:
            value = int(outputs.get(symbol.address))
            if value != recorded[symbol.name]:  # as the program reads them (core/present.py)
                shown = [raw_text(symbol.type.value, v, symbol.scaling)
                         for v in (recorded[symbol.name], value)]
                diffs.append(f"{symbol.name} recorded {shown[0]}, replay {shown[1]}")
    if not diffs:
        return "differs (the trace names no output symbols: it predates them, or memory differs)"
    more = f" and {len(diffs) - 3} more" if len(diffs) > 3 else ""
    return "differs: " + "; ".join(diffs[:3]) + more
