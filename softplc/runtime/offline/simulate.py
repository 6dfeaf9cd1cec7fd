"""Simulation in virtual time: the same scans as the real loop, as fast as the machine allows.

Owns: `simulate()` and its report (the `softplc simulate --json` object), the playing of a
script (timed HMI writes and input overrides, runtime/offline/simscript.py) into the scans, and the
timeline: the scans in which outputs, memory, marking or events changed; breakpoints
(docs/debug.md): the simulation ends at the pause, after `step` more scans if asked.
Does not know: processes, sockets, the real clock (a virtual clock jumps deadline to deadline).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softplc.core.image import ProcessImage, split_registers
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.plc import ProgramCommand
from softplc.core.present import Shown, shown_number, shown_rounded
from softplc.core.result import ScanResult
from softplc.core.snapshot import HmiWrite
from softplc.core.symbols import Direction, Symbol
from softplc.devices.driver import Health
from softplc.devices.sim import SimDriver
from softplc.runtime.offline.simscript import Script, ScriptPlayer
from softplc.runtime.runner import boot
from softplc.runtime.trace import TraceWriter

SCRIPT_DRIVER = "(script)"  # the pseudo-driver's name in health reports: no io image can clash


class ScriptInputs:
    """A driver that reads last: it overwrites the inputs a script forces (`force:`)."""

    name = SCRIPT_DRIVER

    def __init__(self, player: ScriptPlayer) -> None:
        self.player = player

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        self.player.patch(image)

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        pass

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool:
        return True  # writes nothing: the script only overrides inputs

    def health(self) -> Health:
        return Health.OK


@dataclass(slots=True)
class Timeline:
    """One entry per scan in which something a person would look for happened."""

    watched: tuple[Symbol, ...]  # outputs and memory, by declaration order
    names: dict[str, Symbol]  # address -> symbol, to show HMI writes by name and value
    last: dict[str, int]  # raw bits
    entries: list[dict[str, Any]]

    @classmethod
    def of(cls, net: CompiledNet, image: ProcessImage) -> Timeline:
        watched = tuple(s for s in net.io.symbols.values() if s.direction is not Direction.IN)
        names = {str(s.address): s for s in net.io.symbols.values()}
        return cls(watched, names, {s.name: image.get(s.address) for s in watched}, [])

    def _shown(self, sym: Symbol, raw: int) -> Shown:
        """A value as the timeline shows it: core/present.py's, at the scale's resolution."""
        return shown_rounded(sym.type.value, raw, sym.scaling)

    def _write(self, write: HmiWrite) -> str:
        sym = self.names.get(str(write.address))
        if sym is None or (not sym.address.is_bit and
                           len(write.values) != len(split_registers(0, sym.address.width))):
            return f"{write.address}={','.join(map(str, write.values))}"  # registers as sent
        raw = 0
        for register in write.values:  # most significant first, as Modbus writes them
            raw = (raw << 16) | register
        return f"{sym.name}={self._shown(sym, raw)}"

    def record(self, k: int, now_ns: int, result: ScanResult, image: ProcessImage,
               hmi: tuple[HmiWrite, ...], forced: dict[str, int | str]) -> None:
        values = {s.name: image.get(s.address) for s in self.watched}
        symbols = {s.name: s for s in self.watched}
        changed = {n: self._shown(symbols[n], v)
                   for n, v in values.items() if self.last.get(n) != v}
        self.last = values
        inputs = {s.name: s for s in self.names.values()}
        typed: dict[str, Shown] = {n: v if isinstance(v, str) else self._shown(inputs[n], v)
                                   for n, v in forced.items()}
        entry: dict[str, Any] = {"k": k, "t_s": now_ns / 1e9}
        writes = [self._write(w) for w in hmi]
        for key, value in (("hmi", writes),
                           ("forced", typed), ("fired", list(result.fired)),
                           ("done", list(result.completed)), ("marking", result.marking_changes),
                           ("events", list(result.events)), ("changed", changed)):
            if value:
                entry[key] = value
        if len(entry) > 2:
            self.entries.append(entry)


def simulate(net: CompiledNet, duration_ns: int, period_ns: int = 10_000_000, seed: int = 0,
             trace_path: str | Path | None = None, plant: str | None = None,
             script: Script | None = None, timeline: bool = False,
             breaks: Sequence[str] = (), step: int = 0) -> dict[str, Any]:
    """Run `net` on its simulated plant for `duration_ns` of virtual time, playing `script`.
    With `timeline`, the report has a "timeline" list (see Timeline). `breaks` are breakpoints
    (`fire:T`, `transition:T`, `enabled:T`, `when:EXPR`) set before the first round: the
    simulation ends when the PLC pauses, or `step` scans after that (report: "paused")."""
    if period_ns <= 0:
        raise ValueError("period must be positive")
    trace = TraceWriter(trace_path)
    runner, commands = boot(net, seed, start=True, trace=trace, plant=plant)
    runner.plc.debug.period_ns = period_ns
    commands += [ProgramCommand(Command.BREAK, id=10 + i, symbol=_spec(text), value=0)
                 for i, text in enumerate(breaks)]
    pauses: list[dict[str, Any]] = []
    steps = step
    player = ScriptPlayer(script) if script is not None else None
    if player is not None:
        runner.drivers.append(ScriptInputs(player))
    line = Timeline.of(net, runner.plc.image) if timeline else None
    scans = duration_ns // period_ns
    try:
        for k in range(scans):
            now = k * period_ns
            before = dict(player.forced_values) if player is not None else {}
            hmi = player.due(now) if player is not None else ()
            if k and runner.plc.debug.paused:  # at a breakpoint: a step, or the end
                commands, steps = [ProgramCommand(Command.STEP, id=k, value=steps)], 0
            result = runner.step(now, commands, hmi)
            commands = []
            if refused := [r.message for r in result.replies if not r.ok]:
                raise ValueError("; ".join(refused))
            if (pause := runner.plc.debug.pause) is not None:
                pauses.append({**pause.as_dict(), "t_s": now / 1e9})
                if not steps:
                    scans = k + 1
                    break
            if line is not None:
                after = dict(player.forced_values) if player is not None else {}
                forced: dict[str, int | str] = {n: v for n, v in after.items()
                                                if before.get(n) != v}
                forced.update({n: "released" for n in before if n not in after})
                line.record(k, now, result, runner.plc.image, hmi, forced)
    finally:
        runner.close()
    report = _report(net, runner, scans, period_ns, seed, trace, script, line)
    if breaks:
        report["paused"] = pauses[-1] if pauses and runner.plc.debug.paused else None
        report["pauses"] = pauses
    return report


def _spec(text: str) -> str:
    """`transition:T` (a breakpoint on T firing) as the command's `fire:T`."""
    kind, sep, rest = text.partition(":")
    return f"fire:{rest}" if sep and kind == "transition" else text


def _report(net: CompiledNet, runner: Any, scans: int, period_ns: int, seed: int,
            trace: TraceWriter, script: Script | None, line: Timeline | None) -> dict[str, Any]:
    plc = runner.plc
    plants = [d.plant.report().as_dict() for d in runner.drivers if isinstance(d, SimDriver)]
    outputs = {s.name: shown_number(s.type.value, plc.image.get(s.address), s.scaling)
               for s in net.io.symbols.values() if s.direction.value != "in"}
    report = {
        "program": net.name,
        "program_hash": net.program_hash,
        "scans": scans,
        "duration_s": scans * period_ns / 1e9,
        "period_ms": period_ns / 1e6,
        "seed": seed,
        "state": plc.state.name,
        "fired": dict(sorted(runner.fired_counts.items())),
        "marking": plc.marking(),
        "outputs_final": outputs,
        "plant": plants[0] if len(plants) == 1 else plants,
        "diagnostics": plc.engine.diagnostics if plc.engine else [],
        "diagnostic_count": plc.engine.diagnostic_count if plc.engine else 0,
        "trace_sha256": trace.sha256,
    }
    if script is not None:
        report["script"] = {"file": script.file, "steps": len(script.steps)}
    if line is not None:
        report["timeline"] = line.entries
    return report


def format_timeline(entries: list[dict[str, Any]]) -> list[str]:
    """The timeline for a person: one line per scan, time first."""
    lines = [f"timeline: {len(entries)} scan(s) where outputs, memory, marking or events "
             "changed (t in s of virtual time, k = scan number)"]
    for e in entries:
        parts = []
        if "hmi" in e:
            parts.append("hmi write " + ", ".join(e["hmi"]))
        if "forced" in e:
            parts.append("forced " + ", ".join(f"{n}={v}" for n, v in e["forced"].items()))
        if "fired" in e:
            parts.append("fired " + ", ".join(e["fired"]))
        if "done" in e:
            parts.append("completed " + ", ".join(e["done"]))
        if "marking" in e:
            parts.append("marking " + ", ".join(f"{p}={n}" for p, n in e["marking"].items()))
        if "changed" in e:
            parts.append(", ".join(f"{n}={v}" for n, v in e["changed"].items()))
        if "events" in e:
            parts.append("events " + ", ".join(e["events"]))
        lines.append(f"  t={e['t_s']:10.3f}  k={e['k']:<7d} " + " | ".join(parts))
    return lines
