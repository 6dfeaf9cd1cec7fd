"""Command line: `softplc COMMAND`, the commands listed by `softplc --help`.

Owns: finding the command in cli/table.py and importing only its module (a client command
starts in tens of milliseconds, not the second that numpy and the compiler cost: issue 40),
usage errors with a "did you mean", exit codes, and a console that may go away (a closed
stdout or stderr, `softplc status | head -1`, ends no command and prints no traceback).
Does not know: any command's arguments or how it works.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Iterable, Sequence

from softplc import __version__
from softplc.cli.table import COMMANDS
from softplc.core.errors import SoftplcError

TYPE_CHECKING = False  # typing costs every start (issue 40); mypy reads it
if TYPE_CHECKING:
    from typing import NoReturn

DESCRIPTION = (
    "softplc: a soft PLC whose control programs are Petri nets. Check a program and its "
    "devices, simulate it on a plant model in virtual time, analyse its state space, run it "
    "(a scan process with a Modbus TCP slave, an HTTP API and page, OPC UA), replay a trace, "
    "and drive a running PLC (download, start, stop, force, status, ...). "
    "`softplc COMMAND --help` gives a command's options.")


class _Retry(SoftplcError):
    """A usage error of the quick parser (one command listed): parsed again by the whole one,
    whose message lists every command."""


class _Quick(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        raise _Retry(message)


def _parser(full: Iterable[str], listed: Iterable[str] = COMMANDS,
            kind: type[argparse.ArgumentParser] = argparse.ArgumentParser
            ) -> argparse.ArgumentParser:
    """The commands `listed` with their help; those in `full` with their arguments too."""
    parser = kind(prog="softplc", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"softplc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    stubs = {name: sub.add_parser(name, help=COMMANDS[name].help) for name in listed}
    for name in full:
        entry = COMMANDS[name]
        getattr(importlib.import_module(entry.module), entry.add)(stubs[name])
        if entry.program:  # a program file: --pou NAME of a PLCopen XML one (docs/sfc.md)
            from softplc.cli.pou import add_pou

            add_pou(stubs[name], entry.program)
    return parser


def _finish(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.Namespace:
    """`--pou NAME` folded into the program (FILE.xml#NAME); what cannot mean anything is a
    usage error here, before the command runs."""
    dest = COMMANDS[args.command].program
    if dest and getattr(args, "pou", None) is not None:
        from softplc.cli.pou import fold, label

        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        command = sub.choices[args.command]  # its usage line, as for its other usage errors
        try:
            setattr(args, dest, fold(getattr(args, dest), args.pou, label(command, dest)))
        except ValueError as exc:
            command.error(str(exc))
    return args


def build_parser() -> argparse.ArgumentParser:
    """The whole parser, every command's module imported (tests and documentation read it)."""
    return _parser(COMMANDS)


def _command_of(argv: Sequence[str]) -> str | None:
    """The command word: the first argument that is no option (the top level has only
    options without values: --help, --version)."""
    return next((arg for arg in argv if not arg.startswith("-")), None)


def parse(argv: Sequence[str]) -> argparse.Namespace:
    """Parse `argv`, building only the parser of the command it names."""
    if list(argv) == ["--version"]:  # as argparse's version action prints it, with no parser
        print(f"softplc {__version__}")
        raise SystemExit(0)
    command = _command_of(argv)
    if command in COMMANDS and argv[0] == command:  # no top-level option: -h lists them all
        try:  # a parser of this command alone: the other 30 stubs cost ~8 ms (issue 40)
            quick = _parser([command], [command], _Quick)
            return _finish(quick, quick.parse_args(argv))
        except _Retry:
            pass  # a usage error, worded below as always (the usage line lists every command)
    if command is None or command in COMMANDS:
        whole = _parser([command] if command else [])
        return _finish(whole, whole.parse_args(argv))
    import difflib  # only for a mistyped command

    near = difflib.get_close_matches(command, COMMANDS, n=1)
    hint = f" (did you mean {near[0]!r}?)" if near else ""
    _parser([]).error(f"unknown command {command!r}{hint}; `softplc --help` lists them")


class _Console:
    """sys.stdout or sys.stderr that a closed pipe (`| head -1`) silences instead of raising:
    the command finishes, a running PLC goes on, the interpreter's last flush hits /dev/null."""

    def __init__(self, stream: object) -> None:
        self._stream, self._gone = stream, False

    def _quietly(self, call: str, *args: str) -> object:
        try:
            return None if self._gone else getattr(self._stream, call)(*args)
        except BrokenPipeError:
            self._gone, null = True, os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())  # type: ignore[attr-defined]
            os.close(null)
            return None

    def write(self, text: str) -> object:
        return self._quietly("write", text) or len(text)

    def flush(self) -> None:
        self._quietly("flush")

    def __getattr__(self, name: str) -> object:
        return getattr(self._stream, name)


def main(argv: Sequence[str] | None = None) -> int:
    streams = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Console(sys.stdout), _Console(sys.stderr)
    try:
        args = parse(sys.argv[1:] if argv is None else argv)  # --help, usage: SystemExit
        return int(args.func(args))
    finally:
        sys.stdout.flush()  # a closed pipe is found here, not in the interpreter's exit
        sys.stderr.flush()
        sys.stdout, sys.stderr = streams
