"""The CLI's own offline commands: `softplc check`, `simulate`, `replay` and `bench`.

Owns: their arguments, exit codes (0 done, 1 a bad program or input with every problem on
stderr) and what a person reads. Does not know: how a program compiles, simulates or replays
(program/, runtime/), nor the other commands (cli/table.py lists them all).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path

from softplc.cli.argtypes import duration as _duration
from softplc.core.problems import Problem, ProgramError
from softplc.program.compiler import compile_file, summarize
from softplc.program.io_image import load_io_image
from softplc.program.spec import TOP_KEYS
from softplc.program.yamlload import load_yaml

PROGRAM_KEYS = TOP_KEYS - {"description", "events"}  # only a program or subnet has these


def _report_problems(path: str, problems: Sequence[Problem]) -> None:
    for problem in problems:
        print(problem, file=sys.stderr)
    print(f"{path}: {len(problems)} problem(s)", file=sys.stderr)


def _compile_or_report(path: str):  # type: ignore[no-untyped-def]
    try:
        return compile_file(path)
    except ProgramError as exc:
        _report_problems(path, exc.problems)
        return None


def _is_symbols_file(path: str) -> bool:
    """A symbols file (io_images/*.yaml) rather than a program: `symbols:` and no net keys."""
    try:
        data, _ = load_yaml(Path(path).read_text(encoding="utf-8"), path)
    except (OSError, UnicodeDecodeError):
        return False  # compile_file reports it
    return isinstance(data, dict) and "symbols" in data and not PROGRAM_KEYS & set(data)


def cmd_check(args: argparse.Namespace) -> int:
    """Validate everything that can be known without opening a device: the program, its
    symbols file, and the drivers' plants and channels. Given a symbols file, just that."""
    from softplc.devices.check import check_devices

    if Path(args.program).suffix.lower() == ".pnml":
        from softplc.analysis.cli import check_pnml

        return check_pnml(args.program, lambda io: check_devices(io, args.plant,
                                                                 need_plant=False))
    if _is_symbols_file(args.program):
        try:
            io = load_io_image(args.program)
        except ProgramError as exc:
            _report_problems(args.program, exc.problems)
            return 1
        problems = check_devices(io, args.plant, need_plant=False)
        if problems:
            _report_problems(args.program, problems)
            return 1
        kinds = ", ".join(f"{d.name} ({d.kind})" for d in io.drivers.values()) or "none"
        print(f"symbols {args.program}: {len(io.symbols)} symbols, {len(io.events)} events, "
              f"drivers: {kinds}")
        return 0
    net = _compile_or_report(args.program)
    if net is None:
        return 1
    problems = check_devices(net.io, args.plant, need_plant=False)
    if problems:
        _report_problems(args.program, problems)
        return 1
    print(summarize(net))
    from softplc.analysis.cli import check_summary

    check_summary(net)  # warnings only: check's exit code is the compiler's
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    from softplc.devices.check import check_devices
    from softplc.devices.driver import DeviceError
    from softplc.runtime.offline.simscript import load_script
    from softplc.runtime.offline.simulate import format_timeline, simulate

    net = _compile_or_report(args.program)
    if net is None:
        return 1
    problems = check_devices(net.io, args.plant)
    script = None
    if args.script:
        try:
            script = load_script(args.script, net.io)
        except ProgramError as exc:
            problems = [*problems, *exc.problems]
    if problems:
        _report_problems(args.program, problems)
        return 1
    try:
        report = simulate(net, args.duration, args.period, args.seed, args.trace,
                          plant=args.plant, script=script, timeline=args.timeline)
    except (DeviceError, ValueError, OSError) as exc:  # a device or file the checks let by
        print(f"{args.program}: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(report, sort_keys=True))
        return 0
    plant = report["plant"]
    print(f"{report['program']}: {report['scans']} scans, {report['duration_s']:.0f} s virtual, "
          f"state {report['state']}")
    if isinstance(plant, dict):
        print(f"plant: {plant['parts_in']} in, {plant['parts_out']} out, "
              f"{plant['parts_drilled']} drilled, {len(plant['faults'])} fault(s)")
        for fault in plant["faults"]:
            print(f"  fault: {fault}")
    if script is not None:
        print(f"script: {script.file}, {len(script.steps)} step(s)")
    print(f"fired: {report['fired']}")
    diagnostics = report["diagnostics"]
    if report["diagnostic_count"]:  # run-time errors of guards and actions: never silent
        print(f"diagnostics: {report['diagnostic_count']} (the first {min(5, len(diagnostics))}"
              " shown; all in --json)")
        for diagnostic in diagnostics[:5]:
            print(f"  {diagnostic}")
    for line in format_timeline(report["timeline"]) if args.timeline else []:
        print(line)
    print(f"trace sha256: {report['trace_sha256']}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from softplc.debug.replay import replay

    net = _compile_or_report(args.program)
    if net is None:
        return 1
    try:
        result = replay(args.trace, net)
    except OSError as exc:  # one line, never a traceback
        print(f"softplc replay: cannot read trace {args.trace}: {exc.strerror}", file=sys.stderr)
        return 1
    except (ValueError, KeyError, TypeError) as exc:
        print(f"softplc replay: {args.trace}: not a usable trace ({exc})", file=sys.stderr)
        return 1
    if result.ok:
        print(f"replay: {result.scans} scans reproduced bit for bit")
        return 0
    print(f"replay: first divergence at {result.divergence}", file=sys.stderr)
    return 1


def cmd_bench(args: argparse.Namespace) -> int:
    try:
        from softplc.bench.harness import main as bench_main
    except ImportError as exc:  # matplotlib and snakes come with the `bench` extra
        print(f"softplc bench: {exc}; install the bench extra: pip install -e '.[bench]'",
              file=sys.stderr)
        return 2
    return int(bench_main(args))


def add_check(check: argparse.ArgumentParser) -> None:
    check.add_argument("program", help="a program, a PNML net (.pnml), or a symbols file "
                       "(io_images/*.yaml)")
    check.add_argument("--plant", help="plant model for sim drivers that name none "
                       "(as run and simulate take it; default: the io image's)")
    check.set_defaults(func=cmd_check)


def add_simulate(sim: argparse.ArgumentParser) -> None:
    sim.add_argument("program", help="program file (YAML) whose io image names sim drivers")
    sim.add_argument("--plant", help="plant model (default: the one the io image declares)")
    sim.add_argument("--duration", type=_duration, default=600_000_000_000,
                     help="virtual time to simulate, e.g. 90s, 10min (default: 10min)")
    sim.add_argument("--period", type=_duration, default=10_000_000,
                     help="scan period in virtual time (default: 10ms)")
    sim.add_argument("--seed", type=int, default=0,
                     help="seed of the plant's random arrivals (default: 0)")
    sim.add_argument("--json", action="store_true",
                     help="print one JSON object instead of the summary (default: off)")
    sim.add_argument("--trace", metavar="FILE",
                     help="record every scan to this JSON Lines file (default: no trace)")
    sim.add_argument("--script", help="YAML of timed HMI writes and input overrides "
                     "(- at: 5s / write: {hold: true}; docs/simulate.md; default: none)")
    sim.add_argument("--timeline", action="store_true",
                     help="list the scans where outputs, memory, marking or events changed "
                     "(default: off)")
    sim.set_defaults(func=cmd_simulate)
    from softplc.debug.breakcli import add_simulate_options
    add_simulate_options(sim)  # --break, --step (docs/debug.md)


def add_replay(rep: argparse.ArgumentParser) -> None:
    rep.add_argument("trace", help="a JSON Lines trace written by run or simulate --trace")
    rep.add_argument("program", help="the program the trace was recorded with")
    rep.set_defaults(func=cmd_replay)


def add_bench(bench: argparse.ArgumentParser) -> None:
    bench.add_argument("--quick", action="store_true",
                       help="small sizes, short runs (< 2 min) (default: off, full sizes)")
    bench.add_argument("--json", dest="json_file", metavar="FILE",
                       help="write every figure to this JSON file (default: none)")
    bench.add_argument("--plots", metavar="DIR",
                       help="write PNG plots into this directory (default: no plots)")
    bench.add_argument("--markdown", metavar="FILE",
                       help="write the report, e.g. BENCHMARKS.md (default: no report)")
    bench.add_argument("--only", help="comma-separated sections: engine, scan, modbus, "
                       "online_change, memory, web, analysis, opcua, cli (default: all)")
    bench.add_argument("--quiet", action="store_true", help="no progress display (default: off)")
    bench.set_defaults(func=cmd_bench)
