"""`--pou NAME` on every command that takes a program (issue 42): the one SFC POU of a
PLCopen XML file, the same as writing the program `FILE.xml#NAME` (docs/sfc.md).

Owns: adding the option to a command's parser (cli/table.py names the commands and where
their program goes) and folding it into the program argument, refusing at parse time
what cannot mean anything: a different `#POU` in the path, a program that is no PLCopen
XML (a YAML program, a PNML net), no program at all. Reads at most the file's first 4 KiB;
imports nothing of the sfc room (the chart is read when the command runs).
Does not know: how a chart is read or which POUs a file holds (sfc/pous.py says that, and
lists them, when the command runs).
"""

from __future__ import annotations

import argparse

SNIFF = 4096  # the PLCopen namespace is on the root element, at the top of the file


def label(parser: argparse.ArgumentParser, dest: str) -> str:
    """How the command's usage writes its program: PROGRAM, or --program for an option."""
    option = any(a.dest == dest and a.option_strings for a in parser._actions)
    return f"--{dest}" if option else dest.upper()


def add_pou(parser: argparse.ArgumentParser, dest: str) -> None:
    where = label(parser, dest)
    parser.add_argument("--pou", metavar="NAME", default=None,
                        help=f"the SFC POU of the PLCopen XML {where} to use when the file "
                        f"has several; the same as {where} FILE.xml#NAME (docs/sfc.md)")


def fold(program: str | None, pou: str, where: str) -> str:
    """`program` naming the POU `pou`: FILE.xml#POU. Raises ValueError (a usage error)."""
    if not pou.strip():
        raise ValueError("--pou: expected the name of an SFC POU, got nothing")
    if program is None:
        raise ValueError(f"--pou {pou} names an SFC POU of a program file: give the program "
                         f"too ({where} FILE.xml)")
    name, sep, named = program.partition("#")
    if sep and named.upper() != pou.upper():
        raise ValueError(f"--pou {pou} and {program} name different POUs ({pou}, {named}): "
                         "name it once")
    if not name.lower().endswith(".xml"):
        raise ValueError(f"--pou {pou}: {name} is not a PLCopen XML file (.xml); --pou names "
                         "an SFC POU of one (a YAML program is one net)")
    try:
        with open(name, "rb") as f:
            head = f.read(SNIFF)
    except OSError:
        head = b"plcopen.org/xml"  # the command says the file cannot be read, as without --pou
    if b"plcopen.org/xml" not in head:
        raise ValueError(f"--pou {pou}: {name} is not a PLCopen TC6 project (no PLCopen "
                         "namespace: a PNML net?); --pou names an SFC POU of a PLCopen XML file")
    return f"{name}#{named or pou}"
