"""Command line: `softplc check|run|simulate|replay|download|start|stop|resume|reset|kill|status|bench`.

Owns: argument parsing, exit codes, what a person sees. Does not know: how any of it works.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file, summarize


def cmd_check(args: argparse.Namespace) -> int:
    try:
        net = compile_file(args.program)
    except ProgramError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        print(f"{args.program}: {len(exc.problems)} problem(s)", file=sys.stderr)
        return 1
    print(summarize(net))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="softplc", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check", help="validate and compile a program; print a summary")
    check.add_argument("program")
    check.set_defaults(func=cmd_check)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    result: int = args.func(args)
    return result


if __name__ == "__main__":
    sys.exit(main())
