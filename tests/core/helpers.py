"""Shared test helpers for the core: compile a program text, a plain EvalContext, a PLC driver.

Programs are compiled through the real compiler (program/), then exercised through the pure
core only: no socket, no clock, no sleep. Time is a plain `now_ns` argument.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

from softplc.core.expr import Value
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.result import ScanResult
from softplc.core.scan import scan
from softplc.core.snapshot import HmiWrite
from softplc.program.compiler import compile_text

IO_TEXT = """\
symbols:
  a:   {address: "%IX0.0", type: bool}
  b:   {address: "%IX0.1", type: bool}
  w:   {address: "%IW0", type: word}
  q:   {address: "%QX0.0", type: bool, safe: true}
  r:   {address: "%QX0.1", type: bool}
  qw:  {address: "%QW0", type: word, safe: 7}
  m:   {address: "%MX0.0", type: bool}
  mw:  {address: "%MW0", type: word}
"""


def write_io(directory: Path) -> Path:
    path = directory / "io.yaml"
    path.write_text(IO_TEXT, encoding="utf-8")
    return path


def compile_program(directory: Path, body: str, name: str = "prog") -> CompiledNet:
    """Compile `body` (places:/transitions:/... of a program) against io.yaml in `directory`."""
    if not (directory / "io.yaml").exists():
        write_io(directory)
    text = f"program: {name}\nio_image: io.yaml\n{body}"
    return compile_text(text, str(directory / f"{name}.yaml"))


class Ctx:
    """An EvalContext over plain dicts: current values, previous values, events, tokens."""

    def __init__(self, values: Mapping[str, int] | None = None,
                 previous: Mapping[str, int] | None = None, events: Iterable[str] = (),
                 tokens: Mapping[str, Mapping[str, Value]] | None = None) -> None:
        self.values = dict(values or {})
        self.prev = dict(previous or {})
        self.events = set(events)
        self.tokens = dict(tokens or {})

    def symbol(self, name: str) -> int:
        return self.values.get(name, 0)

    def previous(self, name: str) -> int:
        return self.prev.get(name, 0)

    def event(self, name: str) -> bool:
        return name in self.events

    def token(self, var: str) -> Mapping[str, Value]:
        return self.tokens[var]


class Bench:
    """A PLC on a test bench: set inputs by symbol name, scan at a given time, read symbols."""

    def __init__(self, net: CompiledNet, start: bool = True) -> None:
        self.net = net
        self.plc = Plc.empty(ProcessImage(net.io.sizes))
        self.inputs = ProcessImage(net.io.sizes)
        commands = [ProgramCommand(Command.DOWNLOAD, net)]
        if start:
            commands.append(ProgramCommand(Command.START))
        self.last = self.scan(0, commands)

    def set(self, **values: int) -> None:
        for name, value in values.items():
            self.inputs.set(self.net.io.symbols[name].address, value)

    def scan(self, now_ns: int, commands: Iterable[ProgramCommand] = (),
             hmi: Iterable[HmiWrite] = ()) -> ScanResult:
        self.last = scan(self.plc, self.inputs, now_ns, list(commands), list(hmi))
        return self.last

    def get(self, name: str) -> int:
        return self.plc.image.get(self.net.io.symbols[name].address)

    def marking(self) -> dict[str, int]:
        return self.plc.marking()
