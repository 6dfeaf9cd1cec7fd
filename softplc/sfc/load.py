"""The one door from a PLCopen XML file to the program compiler: read, verify, translate.

Owns: `FILE.xml#POU` naming, the optional `FILE.io.yml` beside the chart (its drivers:,
image: and events: head the generated symbols file: the XML has no notion of a driver), and
putting the compiler's findings and the net's place/transition locations back on XML lines.
Does not know: how the YAML it hands over is compiled (program/compiler.py calls it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from softplc.core.net import CompiledNet
from softplc.core.problems import Problem, ProgramError
from softplc.sfc.emit import Emitted, emit
from softplc.sfc.model import Chart
from softplc.sfc.reader import read_chart
from softplc.sfc.verify import verify


@dataclass(frozen=True, slots=True)
class ChartProgram:
    chart: Chart
    file: str  # the XML file
    emitted: Emitted
    sidecar: str | None  # FILE.io.yml when one was read
    notes: tuple[Problem, ...] = ()  # findings that do not refuse the chart (final steps)

    @property
    def program_text(self) -> str:
        return self.emitted.program

    @property
    def io_text(self) -> str:
        return self.emitted.io

    def located(self, exc: ProgramError) -> ProgramError:
        """The compiler's findings on the generated text, put on the XML's lines."""
        head = len(_head(self.sidecar)) if self.sidecar else 0
        out = []
        for p in exc.problems:
            if p.file != self.file:
                out.append(p)
            elif p.path.startswith(("symbols", "drivers", "image", "events")) or \
                    "symbols file" in p.message:
                if self.sidecar and 1 < p.line <= head + 1:
                    out.append(dataclasses.replace(p, file=self.sidecar, line=p.line - 1))
                else:
                    out.append(dataclasses.replace(
                        p, line=self.emitted.io_lines.get(p.line, self.chart.pou_line)))
            else:
                nearest = [x for y, x in sorted(self.emitted.program_lines.items())
                           if y <= p.line]
                out.append(dataclasses.replace(
                    p, line=nearest[-1] if nearest else self.chart.pou_line))
        return ProgramError(sorted(set(out)))

    def compiled(self, build: Callable[[], CompiledNet]) -> CompiledNet:
        """`build` compiles the generated text (program/compiler.py, which this room may not
        import): its findings and its net come back on the XML's lines."""
        try:
            net = build()
        except ProgramError as exc:
            raise self.located(exc) from None
        return self.relocate(net)

    def relocate(self, net: CompiledNet) -> CompiledNet:
        """Places and transitions located at their step's and transition's XML line."""
        lines = self.emitted.program_lines
        return dataclasses.replace(
            net,
            place_where=tuple((self.file, lines.get(line, line)) for _, line in net.place_where),
            transition_where=tuple((self.file, lines.get(line, line))
                                   for _, line in net.transition_where))


def _head(sidecar: str) -> list[str]:
    return Path(sidecar).read_text(encoding="utf-8").splitlines()


def load_chart(path: str | Path, pou: str | None = None, io_name: str = "") -> ChartProgram:
    """Read and verify the chart; raises ProgramError (XML lines) on any problem."""
    name, _, from_path = str(path).partition("#")
    if pou and from_path and pou.upper() != from_path.upper():
        raise ProgramError([Problem(name, 0, "", f"{path} and the POU {pou!r} name different "
                                    "POUs: name it once")])
    pou = pou or from_path or None
    try:
        data = Path(name).read_bytes()
    except OSError as exc:
        raise ProgramError([Problem(name, 0, "", f"cannot read chart: {exc.strerror}")]) \
            from None
    chart = read_chart(data, name, pou)
    notes: list[Problem] = []
    problems = verify(chart, notes)
    sidecar = Path(name).with_suffix(".io.yml")  # not .yaml: programs/*.yaml are nets
    head = ""
    if sidecar.is_file():
        head = sidecar.read_text(encoding="utf-8")
        if any(line.startswith("symbols:") for line in head.splitlines()):
            problems.append(Problem(str(sidecar), 1, "symbols", "the file beside a chart gives "
                                    "drivers:, image: and events: only; the symbols come from "
                                    "the chart's variables"))
    emitted, more = emit(chart, io_name or f"{chart.pou}.io.yaml", head)
    if problems or more:
        raise ProgramError(sorted(set(problems + more)))
    return ChartProgram(chart, name, emitted, str(sidecar) if head else None, tuple(notes))


def is_plcopen(path: str | Path) -> bool:
    """A PLCopen project (not PNML, which is .xml too): its root names a PLCopen namespace."""
    try:
        with open(str(path).partition("#")[0], "rb") as f:
            return b"plcopen.org/xml" in f.read(4096)
    except OSError:
        return False
