"""Simulation scripts: timed HMI writes and input overrides for `softplc simulate --script`.

Owns: the script format (a YAML list of steps, each `at:` a time with `write:`, `force:` and
`release:`), its validation with located problems, and the per-scan application: which HMI
writes a scan receives and which input values it sees forced.
Does not know: drivers, plants, the scan itself (it gives the scan HmiWrite values and patches
the input image the drivers filled).

    - at: 5s
      write: {hold: true}        # an HMI write (as Modbus or PUT /symbols): memory or outputs
    - at: 12s
      force: {s1_i: true}        # an input override: the scan sees this value, not the device's
    - at: 12500ms
      force: {level: 47.5, temp: {raw: 120}}  # engineering units; {raw: N} before scaling
    - at: 13s
      release: [s1_i]            # the device's value again (`release: all`: every override)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softplc.core.image import ProcessImage, split_registers
from softplc.core.present import ValueRefused, accepted
from softplc.core.problems import Problem, ProgramError
from softplc.core.snapshot import HmiWrite
from softplc.core.symbols import Direction, IoImage, Symbol
from softplc.core.units import parse_duration_ns
from softplc.program.suggest import did_you_mean, did_you_mean_key
from softplc.program.yamlload import YList, YMap, line_of, load_yaml, trap_hint

STEP_KEYS = ("at", "write", "force", "release")
RAW_KEY = "raw"  # `{raw: N}`: a value given before scaling (docs/simulate.md)


@dataclass(frozen=True, slots=True)
class Step:
    at_ns: int
    writes: tuple[HmiWrite, ...]
    force: tuple[tuple[Symbol, int], ...]
    release: tuple[str, ...] | None  # input symbols released (None: none)
    release_all: bool  # `release: all`
    line: int


@dataclass(frozen=True, slots=True)
class Script:
    file: str
    steps: tuple[Step, ...]  # in time order (stable for equal times)


class _Reader:
    def __init__(self, file: str, io: IoImage) -> None:
        self.file, self.io = file, io
        self.problems: list[Problem] = []

    def problem(self, line: int, path: str, message: str) -> None:
        self.problems.append(Problem(self.file, line, path, message))

    def step(self, index: int, item: Any, line: int) -> Step | None:
        path = f"[{index}]"
        if not isinstance(item, YMap):
            self.problem(line, path, "expected a step {at: TIME, write: {...}, force: {...}, "
                                     "release: [...]}")
            return None
        for key in item:
            if key not in STEP_KEYS:
                self.problem(line_of(item, key), f"{path}.{key}", f"unknown key {key!r}"
                             f"{did_you_mean_key(key, STEP_KEYS)}; expected one of "
                             f"{', '.join(STEP_KEYS)}")
        at_ns = self.at(item, path, line)
        if not any(k in item for k in STEP_KEYS[1:]):
            self.problem(line, path, "a step needs write:, force: or release:")
        writes = self.values(item, "write", path, want_input=False)
        force = self.values(item, "force", path, want_input=True)
        release, release_all = self.release(item, path)
        if at_ns is None:
            return None
        hmi = tuple(HmiWrite(sym.address, (value,) if sym.address.is_bit else
                             tuple(split_registers(value, sym.address.width)))
                    for sym, value in writes)  # a 32/64-bit value whole, as Modbus writes it
        return Step(at_ns, hmi, tuple(force), release, release_all, line)

    def at(self, item: YMap, path: str, line: int) -> int | None:
        if "at" not in item:
            self.problem(line, path, "missing at: (when, from the start, e.g. 5s)")
            return None
        text = item["at"]
        try:
            return parse_duration_ns(str(text)) if not isinstance(text, bool) else None
        except ValueError as exc:
            self.problem(line_of(item, "at"), f"{path}.at", str(exc))
            return None

    def values(self, item: YMap, key: str, path: str, want_input: bool) -> list[tuple[Symbol, int]]:
        section = item.get(key)
        if section is None:
            return []
        where = f"{path}.{key}"
        if not isinstance(section, YMap):
            self.problem(line_of(item, key), where, "expected a mapping of symbol: value")
            return []
        out = []
        for name, value in section.items():
            sym = self.symbol(name, line_of(section, name), f"{where}.{name}", want_input)
            if sym is not None and (v := self.value(sym, value, line_of(section, name),
                                                     f"{where}.{name}")) is not None:
                out.append((sym, v))
        return out

    def symbol(self, name: Any, line: int, path: str, want_input: bool) -> Symbol | None:
        sym = self.io.symbols.get(str(name))
        if sym is None:
            self.problem(line, path, f"unknown symbol {name!r} (not in {self.io.path})"
                                     f"{did_you_mean(name, self.io.symbols)}")
            return None
        if want_input and sym.direction is not Direction.IN:
            self.problem(line, path, f"{sym.name} is {sym.direction.value} ({sym.address}): "
                                     "force: overrides inputs; use write: for it")
            return None
        if not want_input and sym.direction is Direction.IN:
            self.problem(line, path, f"{sym.name} is an input ({sym.address}): an HMI cannot "
                                     "write it; use force: to override it")
            return None
        return sym

    def value(self, sym: Symbol, value: Any, line: int, path: str) -> int | None:
        """The raw bits a write or force of `value` stores in `sym`, or None (a problem): a
        value as `softplc force` and the API take it (core/present.py: a scaled symbol in
        engineering units), or `{raw: N}`, the value of the symbol's type before scaling."""
        scale = sym.scaling
        if isinstance(value, YMap | dict):
            if set(value) != {RAW_KEY}:
                self.problem(line, path, f"{sym.name}: expected a value or {{{RAW_KEY}: N}} "
                                         f"(the raw value, before scaling), got {dict(value)!r}")
                return None
            value, scale = value[RAW_KEY], None
        try:
            return accepted(sym.type.value, value, sym.name, scale)
        except ValueRefused as exc:
            self.problem(line, path, f"{exc}{trap_hint(value)}")
            return None

    def release(self, item: YMap, path: str) -> tuple[tuple[str, ...] | None, bool]:
        value = item.get("release")
        if value is None:
            return None, False
        if value == "all":
            return (), True
        names = [value] if isinstance(value, str) else value
        if not isinstance(names, YList | list):
            self.problem(line_of(item, "release"), f"{path}.release",
                         "expected a list of input symbols, or all")
            return None, False
        found = [s.name for n in names if (s := self.symbol(
            n, line_of(item, "release"), f"{path}.release", want_input=True)) is not None]
        return tuple(found), False


def parse_script(text: str, filename: str, io: IoImage) -> Script:
    """Validate a script against the program's symbols. Raises ProgramError with every problem."""
    data, problems = load_yaml(text, filename)
    reader = _Reader(filename, io)
    reader.problems.extend(problems)
    if not problems and not isinstance(data, YList):
        reader.problem(getattr(data, "line", 1), "", "expected a list of steps: - at: 5s ...")
    steps = []
    if isinstance(data, YList):
        for i, item in enumerate(data):
            step = reader.step(i, item, line_of(data, i))
            if step is not None:
                steps.append(step)
    if reader.problems:
        raise ProgramError(sorted(reader.problems))
    return Script(filename, tuple(sorted(steps, key=lambda s: s.at_ns)))


def load_script(path: str | Path, io: IoImage) -> Script:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProgramError([Problem(str(path), 0, "", f"cannot read script: {exc.strerror}")]) \
            from None
    return parse_script(text, str(path), io)


class ScriptPlayer:
    """Steps due by each scan's time: HMI writes for that scan, forced inputs from then on.

    A released input is the device's again from the next read. An input no driver reads
    (`driver: none`) gets back the value it had before it was first forced."""

    def __init__(self, script: Script) -> None:
        self._steps: Sequence[Step] = script.steps
        self._next = 0
        self.forced: dict[str, tuple[Symbol, int]] = {}
        self._before: dict[str, tuple[Symbol, int]] = {}  # undriven inputs: value before force
        self._restore: list[tuple[Symbol, int]] = []

    def due(self, now_ns: int) -> tuple[HmiWrite, ...]:
        """Apply the steps due at `now_ns` (forces, releases); return their HMI writes."""
        writes: list[HmiWrite] = []
        while self._next < len(self._steps) and self._steps[self._next].at_ns <= now_ns:
            step = self._steps[self._next]
            self._next += 1
            names = list(self.forced) if step.release_all else list(step.release or ())
            for name in names:
                if self.forced.pop(name, None) is not None and name in self._before:
                    self._restore.append(self._before.pop(name))
            self.forced.update({sym.name: (sym, value) for sym, value in step.force})
            writes.extend(step.writes)
        return tuple(writes)

    def patch(self, inputs: ProcessImage) -> None:
        """Overwrite the forced inputs in the image the drivers just filled."""
        for sym, value in self._restore:
            inputs.set(sym.address, value)
        self._restore.clear()
        for name, (sym, value) in self.forced.items():
            if sym.driver is None and name not in self._before:
                self._before[name] = (sym, inputs.get(sym.address))
            inputs.set(sym.address, value)

    @property
    def forced_values(self) -> Mapping[str, int]:
        return {name: value for name, (_, value) in self.forced.items()}
