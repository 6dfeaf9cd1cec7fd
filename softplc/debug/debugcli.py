"""The debugging commands of the CLI (issue 32): `softplc why`, `softplc vcd`, `softplc
break|step|continue` and simulate's `--break`/`--step` (added to its parser here).

Owns: their arguments, exit codes (0 answered, 1 refused or unusable input, 2 no API
answering) and what a person reads. `why` asks a running softplc (GET /api/v1/why/NAME) or,
with --trace, replays a trace to the scan asked (debug/tracewalk.py); `vcd` writes a trace
as a value change dump (debug/vcd.py).
Does not know: how a transition is explained (core/why.py), HTTP (api/client.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, Any

from softplc.api.clicmds import EXIT_OK, EXIT_REFUSED, call, connection_options
from softplc.core.problems import ProgramError

if TYPE_CHECKING:
    from softplc.api.client import ApiClient
    from softplc.core.net import CompiledNet

_ORDINAL = ("the longest", "the second longest", "the third longest")


def add_why(why: argparse.ArgumentParser) -> None:
    """Each add_* adds a command's arguments to the parser cli/table.py made for it."""
    why.add_argument("transition", nargs="?", help="the transition's name (a subnet's: "
                     "c1.start); without one, on a running PLC: why nothing moves (the "
                     "transitions enabled by the marking that waited longest, and what blocks "
                     "each, in net time)")
    why.add_argument("--trace", metavar="FILE", help="explain a scan of this trace (written "
                     "by run or simulate --trace) instead of the running PLC (default: none)")
    why.add_argument("--program", metavar="PROGRAM", help="with --trace: the program the "
                     "trace was recorded with")
    why.add_argument("--at-scan", metavar="N", type=int, help="with --trace: the scan "
                     "number (k in the trace, the timeline and the VCD)")
    why.add_argument("--json", action="store_true",
                     help="print the answer as JSON (default: off, one line per reason)")
    connection_options(why)
    why.set_defaults(func=cmd_why)


def add_vcd(vcd: argparse.ArgumentParser) -> None:
    vcd.add_argument("trace", help="a JSON Lines trace written by run or simulate --trace")
    vcd.add_argument("program", help="the program the trace was recorded with")
    vcd.add_argument("-o", "--output", metavar="FILE", required=True, help="the VCD file")
    vcd.set_defaults(func=cmd_vcd)


def _compile(path: str, what: str) -> CompiledNet | None:
    # Imported here: `why` on a running PLC is a client command and starts without numpy
    # and the compiler (issue 40).
    from softplc.program.compiler import compile_file

    try:
        return compile_file(path)
    except ProgramError as exc:
        for problem in exc.problems:
            print(problem, file=sys.stderr)
        print(f"{path}: {len(exc.problems)} problem(s)", file=sys.stderr)
    except OSError as exc:
        print(f"softplc {what}: cannot read {path}: {exc.strerror}", file=sys.stderr)
    return None


def _show(answer: dict[str, Any], as_json: bool, when: str) -> None:
    if as_json:
        print(json.dumps(answer, sort_keys=True))
        return
    from softplc.core.why import format_why  # numpy comes with core.why's engine

    lines = format_why(answer)
    lines[0] += f" ({when})"
    if wait := answer.get("waiting"):  # live: one of the longest waits (core/waiting.py)
        lines.append(f"  waited {wait.get('for_s', 0):.1f} s in net time, enabled by the "
                     f"marking without firing ({_ORDINAL[min(int(wait.get('rank') or 0), 2)]}"
                     " wait of the net)")
    for line in lines:
        print(line)
    if answer.get("note"):
        print(f"({answer['note']})")


def _with_wait(client: ApiClient, transition: str) -> dict[str, Any]:
    """The why route's answer, with `waiting`: the transition's wait from the status
    document (core/waiting.py: for_s in net time, blockers), None if it is not among the
    longest waits."""
    answer = client.why(transition)
    waits = client.status().get("waiting") or []
    rank, wait = next(((i, w) for i, w in enumerate(waits)
                       if w.get("transition") == transition), (None, None))
    return {**answer, "waiting": None if wait is None else {**wait, "rank": rank}}


def _waited(wait: dict[str, Any]) -> str:
    what = wait.get("transition") or "the net (a dead marking)"
    return f"{what} waits {wait.get('for_s', 0):.1f} s: {'; '.join(wait.get('blockers') or [])}"


def _show_waits(status: dict[str, Any], as_json: bool) -> None:
    """`softplc why` without a transition: why nothing moves, from the status document."""
    waits, state = status.get("waiting") or [], status.get("state")
    if as_json:
        print(json.dumps({"state": state, "scan": status.get("scan_count"), "waiting": waits},
                         sort_keys=True))
        return
    if not waits:
        print(f"why: nothing waits (state {state}"
              + (", waiting for I/O" if status.get("waiting_for_io") else "")
              + ("" if state == "RUNNING" else ": only a RUNNING PLC waits") + ")")
        return
    print(f"why nothing moves (after scan {status.get('scan_count')}, in net time: a pause "
          "stands still), the longest waits first:")
    for wait in waits:
        print(f"  {_waited(wait)}")
    print("(softplc why TRANSITION explains one)")


def cmd_why(args: argparse.Namespace) -> int:
    if args.trace is None:
        if args.program is not None or args.at_scan is not None:
            print("softplc why: --program and --at-scan go with --trace", file=sys.stderr)
            return EXIT_REFUSED
        if args.transition is None:
            code, status = call(args, "why", lambda client: client.status())
            if code == EXIT_OK:
                _show_waits(status, args.json)
            return code
        code, answer = call(args, "why", lambda client: _with_wait(client, args.transition))
        if code == EXIT_OK:
            _show(answer, args.json, f"the next round, after scan {answer.get('scan')}")
        return code
    if args.transition is None:
        print("softplc why: --trace needs a TRANSITION", file=sys.stderr)
        return EXIT_REFUSED
    if args.program is None or args.at_scan is None:
        print("softplc why: --trace needs --program PROGRAM and --at-scan N", file=sys.stderr)
        return EXIT_REFUSED
    net = _compile(args.program, "why")
    if net is None:
        return EXIT_REFUSED
    from softplc.debug.tracewalk import why_at

    try:
        why = why_at(args.trace, net, args.transition, args.at_scan)
    except KeyError:
        print(f"softplc why: no transition {args.transition!r} in program {net.name} "
              f"(transitions: {', '.join(t.name for t in net.transitions[:50])})",
              file=sys.stderr)
        return EXIT_REFUSED
    except OSError as exc:
        print(f"softplc why: cannot read trace {args.trace}: {exc.strerror}", file=sys.stderr)
        return EXIT_REFUSED
    except ValueError as exc:  # no such scan, no round in it, another program's trace
        print(f"softplc why: {args.trace}: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    _show({**why.as_dict(), "scan": args.at_scan}, args.json, f"scan {args.at_scan}")
    return EXIT_OK


def cmd_vcd(args: argparse.Namespace) -> int:
    from softplc.debug.vcd import write_vcd

    net = _compile(args.program, "vcd")
    if net is None:
        return EXIT_REFUSED
    try:
        # UTF-8: a unit in the header's $comment may be `°C`; all else the VCD writes is ASCII.
        with open(args.output, "w", encoding="utf-8") as out:
            scans = write_vcd(args.trace, net, out)
    except OSError as exc:
        print(f"softplc vcd: {exc.filename}: {exc.strerror}", file=sys.stderr)
        return EXIT_REFUSED
    except (ValueError, KeyError, TypeError) as exc:
        print(f"softplc vcd: {args.trace}: not a usable trace ({exc})", file=sys.stderr)
        return EXIT_REFUSED
    print(f"vcd: {scans} scans of {net.name} written to {args.output}")
    return EXIT_OK
