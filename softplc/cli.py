"""Command line: `softplc COMMAND`, the commands listed by `softplc --help`.

Owns: argument parsing, exit codes, what a person sees, and a console that may go away (a
closed stdout or stderr, `softplc status | head -1`, ends no command and prints no traceback).
Does not know: how any of it works.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from softplc.api.secopts import add_run_options
from softplc.core.problems import Problem, ProgramError
from softplc.core.units import parse_duration_ns
from softplc.program.compiler import compile_file, summarize
from softplc.program.io_image import load_io_image
from softplc.program.spec import TOP_KEYS
from softplc.program.yamlload import load_yaml

PROGRAM_KEYS = TOP_KEYS - {"description", "events"}  # only a program or subnet has these
DESCRIPTION = (
    "softplc: a soft PLC whose control programs are Petri nets. Check a program and its "
    "devices, simulate it on a plant model in virtual time, analyse its state space, run it "
    "(a scan process with a Modbus TCP slave, an HTTP API and page, OPC UA), replay a trace, "
    "and drive a running PLC (download, start, stop, force, status, ...). "
    "`softplc COMMAND --help` gives a command's options.")


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
    from softplc.runtime.simscript import load_script
    from softplc.runtime.simulate import format_timeline, simulate

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
    from softplc.runtime.replay import replay

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


def cmd_run(args: argparse.Namespace) -> int:
    from softplc.runtime.runcmd import run
    return run(args)


def cmd_bench(args: argparse.Namespace) -> int:
    try:
        from softplc.bench.harness import main as bench_main
    except ImportError as exc:  # matplotlib and snakes come with the `bench` extra
        print(f"softplc bench: {exc}; install the bench extra: pip install -e '.[bench]'",
              file=sys.stderr)
        return 2
    return int(bench_main(args))


def _duration(text: str) -> int:
    try:
        return parse_duration_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _timeout(text: str) -> int:
    if (ns := _duration(text)) <= 0:
        raise argparse.ArgumentTypeError(f"expected a duration above 0, got {text!r}")
    return ns


def _count(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(text)


def _endpoint(text: str) -> tuple[str, int] | None:
    if text in ("off", "none"):
        return None
    host, _, port = text.rpartition(":")
    if not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT or off, got {text!r}")
    return (host or "127.0.0.1", int(port))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="softplc", description=DESCRIPTION)
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("check", help="validate and compile a program (or check a symbols "
                           "file), its drivers' plants and channels; opens nothing")
    check.add_argument("program", help="a program, a PNML net (.pnml), or a symbols file "
                       "(io_images/*.yaml)")
    check.add_argument("--plant", help="plant model for sim drivers that name none "
                       "(as run and simulate take it; default: the io image's)")
    check.set_defaults(func=cmd_check)

    run = sub.add_parser("run", help="run a soft PLC (scan process + Modbus/HTTP process)")
    run.add_argument("program", nargs="?",
                     help="program to run; without it, the boot program of --state-dir (the "
                     "last program the PLC accepted), if any")
    run.add_argument("--period", type=_duration, default=10_000_000,
                     help="scan period, e.g. 10ms, 1ms (default: 10ms)")
    run.add_argument("--modbus", type=_endpoint, default=("127.0.0.1", 5020),
                     help="Modbus TCP slave HOST:PORT, or off (default: 127.0.0.1:5020)")
    run.add_argument("--api", type=_endpoint, default=("127.0.0.1", 8080),
                     help="HTTP API HOST:PORT, or off (default: 127.0.0.1:8080)")
    run.add_argument("--opcua", type=_endpoint, default=("127.0.0.1", 4840),
                     help="OPC UA server HOST:PORT, or off (default: 127.0.0.1:4840; "
                     "docs/opcua.md)")
    run.add_argument("--plant", help="plant model for sim drivers whose io image names none "
                     "(transport, drilling, tank); an io image naming its plant keeps it, and a "
                     "contradicting --plant is refused (default: the io image's)")
    run.add_argument("--start", action="store_true",
                     help="start the program at once: warm from a valid snapshot of the same "
                     "program in --state-dir, else cold from the initial marking (default: off, "
                     "the PLC waits STOPPED for `softplc start`)")
    run.add_argument("--state-dir", default="state",
                     help="retain snapshots, their lock, the kept bundle and the API token "
                     "(default: %(default)s)")
    run.add_argument("--retain-interval", type=_duration, default=1_000_000_000,
                     help="write a retain snapshot this often; 0: only on stop (default: 1s)")
    run.add_argument("--warm-start", choices=("run", "stop"), default="run",
                     help="warm restart of a program that was RUNNING: resume it (run) or "
                     "restore it and wait STOPPED for `softplc resume` (stop) "
                     "(default: %(default)s)")
    run.add_argument("--boot-policy", choices=("stop", "warm", "cold"), default=None,
                     help="what a restart of the machine or of softplc run does: stay stopped, "
                     "warm start, cold start; kept in --state-dir for the next runs (default: "
                     "the kept one, else stop; docs/retain.md)")
    run.add_argument("--modbus-writes", choices=("open", "symbols", "none"), default="open",
                     help="Modbus writes allowed: open (outputs and memory, as OpenPLC), "
                     "symbols (only the running program's output and memory symbols not declared "
                     "hmi_writable: false), none (default: %(default)s)")
    run.add_argument("--modbus-max-connections", type=_count, default=16, metavar="N",
                     help="Modbus connection slots; when full, the connection idle longest is "
                     "closed for a new one (default: %(default)s)")
    run.add_argument("--modbus-max-per-peer", type=_count, default=8, metavar="N",
                     help="Modbus connection slots one IP address may hold (default: %(default)s)")
    run.add_argument("--modbus-idle-timeout", type=_timeout, default=60_000_000_000,
                     help="close a Modbus connection without a request for this long "
                     "(default: 60s)")
    run.add_argument("--rt-priority", type=int, metavar="1..99",
                     help="run the scan process with this SCHED_FIFO priority (needs root or "
                     "CAP_SYS_NICE; refused: normal scheduling, said in status; default: normal "
                     "scheduling)")
    run.add_argument("--scan-cpu", type=int, metavar="N",
                     help="pin the scan process to CPU N (default: not pinned)")
    run.add_argument("--busy-wait", action="store_true",
                     help="the scan waits for each slot without sleeping (a CPU always busy): "
                     "for virtual machines, which wake a sleeping CPU late; not with "
                     "--rt-priority (default: sleep)")
    run.add_argument("--programs-dir", metavar="DIR", default=None,
                     help="where a program downloaded as plain YAML text (not a bundle) finds "
                     "its io image and subnets (default: programs/ beside the program's "
                     "folder, else under the current directory)")
    run.add_argument("--trace", metavar="FILE",
                     help="record every scan to this JSON Lines file (default: no trace)")
    run.add_argument("--seed", type=int, default=0,
                     help="seed of the plant's random arrivals (default: %(default)s)")
    run.add_argument("--watchdog", type=float, default=10.0,
                     help="a scan longer than period x this is over budget; "
                     "--watchdog-sensitivity of them in a row fault (default: %(default)s)")
    run.add_argument("--watchdog-sensitivity", type=_count, default=3, metavar="N",
                     help="scans over budget in a row that fault the PLC; 1: the first "
                     "(default: %(default)s)")
    run.add_argument("--watchdog-hard", type=_timeout, default=3_000_000_000,
                     help="one scan this long (and over budget), or one that has not ended "
                     "after this long, faults alone (default: 3s)")
    run.add_argument("--verify", choices=("refuse", "warn", "off"), default="warn",
                     help="analysis gate on every download (docs/analysis.md): refuse nets with "
                     "an unbounded place, a deadlock, a dead transition or an output conflict; "
                     "warn (accept, findings in the reply and status); off (default: %(default)s)")
    run.add_argument("--on-stall", choices=("fault", "continue"), default="fault",
                     help="a scan cycle that starts period x watchdog late is a stall (counted, "
                     "an event); one that is also --stall-fault-after late (process paused, VM "
                     "pause): fault with safe outputs, or go on (default: %(default)s)")
    run.add_argument("--stall-fault-after", type=_duration, default=3_000_000_000,
                     help="how late a cycle must start for --on-stall fault to fault "
                     "(default: 3s; at least period x watchdog)")
    run.add_argument("--duration", type=_duration, help="stop after this long (default: Ctrl-C)")
    run.add_argument("--quiet", action="store_true", help="no live status line (default: off)")
    add_run_options(run)  # --tls, --tls-cert, --tls-key, --trusted-keys (docs/security.md)
    run.set_defaults(func=cmd_run)

    sim = sub.add_parser("simulate", help="run a program on a simulated plant in virtual time")
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

    rep = sub.add_parser("replay", help="re-run a trace's inputs and compare outputs bit for bit")
    rep.add_argument("trace", help="a JSON Lines trace written by run or simulate --trace")
    rep.add_argument("program", help="the program the trace was recorded with")
    rep.set_defaults(func=cmd_replay)

    bench = sub.add_parser("bench", help="benchmarks of the engine, scan timing and Modbus")
    bench.add_argument("--quick", action="store_true",
                       help="small sizes, short runs (< 2 min) (default: off, full sizes)")
    bench.add_argument("--json", dest="json_file", metavar="FILE",
                       help="write every figure to this JSON file (default: none)")
    bench.add_argument("--plots", metavar="DIR",
                       help="write PNG plots into this directory (default: no plots)")
    bench.add_argument("--markdown", metavar="FILE",
                       help="write the report, e.g. BENCHMARKS.md (default: no report)")
    bench.add_argument("--only", help="comma-separated sections: engine, scan, modbus, "
                       "online_change, memory, web, analysis, opcua (default: all)")
    bench.add_argument("--quiet", action="store_true", help="no progress display (default: off)")
    bench.set_defaults(func=cmd_bench)

    from softplc.analysis.cli import add_commands as add_analysis_commands
    from softplc.runtime.debugcli import add_commands as add_debug_commands
    add_analysis_commands(sub)
    add_debug_commands(sub)  # why, vcd (docs/debug.md)
    try:
        from softplc.api.clicmds import add_client_commands
    except ImportError:  # the HTTP client commands need the api package's dependencies
        pass
    else:
        add_client_commands(sub)
    return parser


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
        args = build_parser().parse_args(argv)  # --help and usage errors: SystemExit
        return int(args.func(args))
    finally:
        sys.stdout.flush()  # a closed pipe is found here, not in the interpreter's exit
        sys.stderr.flush()
        sys.stdout, sys.stderr = streams


if __name__ == "__main__":
    sys.exit(main())
