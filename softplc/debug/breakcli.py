"""The CLI of breakpoints and single scans (docs/debug.md): `softplc break add|list|remove|
clear`, `softplc step [N]`, `softplc continue`, and `softplc simulate --break SPEC [--step N]`;
`softplc dap` has its own module, debug/dapserve.py.

Owns: their arguments, what a person reads, exit codes (0 done, 1 refused, 2 no API).
Does not know: HTTP (api/client.py), how a pause works (core/breakpoints.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from typing import Any

from softplc.api.clicmds import EXIT_OK, EXIT_REFUSED, call, connection_options, said


def add_break(brk: argparse.ArgumentParser) -> None:
    """Each add_* adds a command's arguments to the parser cli/table.py made for it."""
    sub = brk.add_subparsers(dest="break_command", required=True, metavar="VERB",
                             help="add, list, remove or clear")
    add = sub.add_parser("add", help="add a breakpoint")
    kinds = add.add_subparsers(dest="kind", required=True, metavar="KIND",
                               help="transition T, or when EXPR")
    on_t = kinds.add_parser("transition", help="on a transition")
    on_t.add_argument("transition", help="its name (a subnet's: c1.start)")
    on_t.add_argument("--on", choices=["fire", "enabled"], default="fire",
                      help="when it fires, or when it becomes enabled (default: %(default)s)")
    on_w = kinds.add_parser("when", help="on a condition becoming true")
    on_w.add_argument("condition", help='a guard expression over symbols, with m("place") '
                      'for a place\'s marking: \'m("c1.full") >= 1 and s1_i\'')
    for parser in (on_t, on_w):
        parser.add_argument("--outputs", choices=["hold", "safe"], default="hold",
                            help="what the devices get while paused (default: %(default)s)")
        connection_options(parser)
        parser.set_defaults(func=cmd_break_add)
    for name, helptext in (("list", "list the breakpoints and the pause"),
                           ("clear", "remove every breakpoint")):
        cmd = sub.add_parser(name, help=helptext)
        connection_options(cmd)
        cmd.set_defaults(func=cmd_break_list if name == "list" else cmd_break_remove, id=None)
    remove = sub.add_parser("remove", help="remove one breakpoint")
    remove.add_argument("id", help="its id (b2 or 2)")
    connection_options(remove)
    remove.set_defaults(func=cmd_break_remove)


def add_step(step: argparse.ArgumentParser) -> None:
    step.add_argument("scans", nargs="?", type=int, default=1, help="N (default: 1)")
    connection_options(step)
    step.set_defaults(func=cmd_step)


def add_continue(cont: argparse.ArgumentParser) -> None:
    connection_options(cont)
    cont.set_defaults(func=cmd_continue)


def _done(args: argparse.Namespace, what: str,
          action: Callable[[Any], dict[str, Any]]) -> int:
    code, reply = call(args, what, action)
    if code == EXIT_OK:
        print(said(what, reply))
    return code


def cmd_break_add(args: argparse.Namespace) -> int:
    on = args.on if args.kind == "transition" else "when"
    target = args.transition if args.kind == "transition" else args.condition
    return _done(args, "break", lambda c: c.add_breakpoint(on, target, args.outputs))


def cmd_break_remove(args: argparse.Namespace) -> int:
    return _done(args, f"break {args.break_command}", lambda c: c.remove_breakpoint(args.id))


def cmd_break_list(args: argparse.Namespace) -> int:
    code, answer = call(args, "break", lambda c: c.breakpoints())
    if code == EXIT_OK:
        for line in format_breakpoints(answer):
            print(line)
    return code


def format_breakpoints(answer: dict[str, Any]) -> list[str]:
    points = answer.get("breakpoints") or []
    lines = [f"  {p.get('text')} (outputs {p.get('outputs')} while paused)" for p in points]
    lines.insert(0, f"breakpoints: {len(points)}")
    paused = answer.get("paused")
    if paused:
        lines.append(f"paused after scan {paused.get('k')} (scan count {paused.get('scan_count')}"
                     f", outputs {paused.get('outputs')}): {paused.get('reason')}")
    elif answer.get("steps_left"):
        lines.append(f"stepping: {answer['steps_left']} scan(s) to go")
    else:
        lines.append("not paused")
    return lines


def cmd_step(args: argparse.Namespace) -> int:
    if not 1 <= args.scans <= 1_000_000:
        print("softplc step: N must be 1..1000000", file=sys.stderr)
        return EXIT_REFUSED
    return _done(args, "step", lambda c: c.step(args.scans))


def cmd_continue(args: argparse.Namespace) -> int:
    return _done(args, "continue", lambda c: c.continue_())


# -- simulate --break ----------------------------------------------------------------------------

def add_simulate_options(sim: argparse.ArgumentParser) -> None:
    """simulate's debugging options: its parser is cli/local.py's, the options and their run
    here."""
    sim.add_argument("--break", dest="breaks", action="append", default=[], metavar="SPEC",
                     help="a breakpoint: transition:T (T fires), enabled:T, when:EXPR; the "
                     "simulation ends when the PLC pauses and reports the scan (repeatable; "
                     "default: none)")
    sim.add_argument("--step", type=int, default=0, metavar="N",
                     help="with --break: run N more scans after the pause, then end "
                     "(default: 0)")
    plain = sim.get_default("func")
    sim.set_defaults(func=lambda args: cmd_simulate_break(args) if args.breaks else plain(args))


def cmd_simulate_break(args: argparse.Namespace) -> int:
    """`simulate` with breakpoints: runs to the pause, prints it (--json: the whole report)."""
    from softplc.core.problems import ProgramError
    from softplc.devices.check import check_devices
    from softplc.devices.driver import DeviceError
    from softplc.program.compiler import compile_file
    from softplc.runtime.offline.simscript import load_script
    from softplc.runtime.offline.simulate import simulate

    try:
        net = compile_file(args.program)
        problems = list(check_devices(net.io, args.plant))
        script = load_script(args.script, net.io) if args.script else None
    except ProgramError as exc:
        problems, net = list(exc.problems), None
    except OSError as exc:
        print(f"softplc simulate: cannot read {exc.filename}: {exc.strerror}", file=sys.stderr)
        return EXIT_REFUSED
    if problems or net is None:
        for problem in problems:
            print(problem, file=sys.stderr)
        print(f"{args.program}: {len(problems)} problem(s)", file=sys.stderr)
        return EXIT_REFUSED
    try:
        report = simulate(net, args.duration, args.period, args.seed, args.trace,
                          plant=args.plant, script=script, timeline=args.timeline,
                          breaks=args.breaks, step=args.step)
    except (DeviceError, ValueError, OSError) as exc:  # a refused breakpoint too
        print(f"softplc simulate: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    if args.json:
        print(json.dumps(report, sort_keys=True))
        return EXIT_OK
    for pause in report["pauses"]:
        print(f"paused after scan {pause['k']} (t={pause['t_s']:.3f} s, scan count "
              f"{pause['scan_count']}): {pause['reason']}")
    if report["paused"] is None:
        print(f"no pause: {report['scans']} scans, {report['duration_s']:.0f} s virtual")
    print(f"state {report['state']}; marking {report['marking']}; fired {report['fired']}")
    return EXIT_OK
