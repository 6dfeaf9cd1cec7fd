"""`softplc import FILE.xml -o DIR`: a PLCopen SFC chart written out as a softplc program.

Owns: the command's arguments and writing DIR/<POU>.yaml and DIR/<POU>.io.yaml, the program
and symbols file the chart compiles to (every command reads the .xml directly too: this is
for taking the chart over into YAML and editing it there).
Does not know: how the chart is read or translated (load.py).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from softplc.core.problems import ProgramError
from softplc.sfc.load import load_chart


def add_import(parser: argparse.ArgumentParser) -> None:
    """`--pou NAME` comes with every command that takes a program (cli/table.py, cli/pou.py):
    it reaches here folded into `chart` as FILE.xml#NAME."""
    parser.add_argument("chart", help="a PLCopen TC6 XML file holding an SFC POU")
    parser.add_argument("-o", "--output", required=True,
                        help="directory for <POU>.yaml and <POU>.io.yaml (created if needed)")
    parser.set_defaults(func=cmd_import)


def cmd_import(args: argparse.Namespace) -> int:
    try:
        chart = load_chart(args.chart)
    except ProgramError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        print(f"{args.chart}: {len(exc.problems)} problem(s); nothing written", file=sys.stderr)
        return 1
    out = Path(args.output)
    pou = chart.chart.pou
    try:
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{pou}.yaml").write_text(chart.program_text, encoding="utf-8")
        (out / f"{pou}.io.yaml").write_text(chart.io_text, encoding="utf-8")
    except OSError as exc:
        print(f"{out}: cannot write: {exc.strerror}", file=sys.stderr)
        return 1
    for note in chart.notes:
        print(note)
    c = chart.chart
    print(f"chart {pou}: {len(c.steps)} steps, {len(c.transitions)} transitions, "
          f"{len(c.actions)} actions -> {out / f'{pou}.yaml'}, {out / f'{pou}.io.yaml'}")
    return 0
