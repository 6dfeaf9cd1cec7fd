"""`softplc run`'s options: the scan period, the doors' endpoints, retain, the watchdog, the
Modbus limits and the security options (api/secopts.py).

Owns: the run parser and its defaults. Does not know: how a PLC runs (runtime/supervise/runcmd.py).
"""

from __future__ import annotations

import argparse
import sys

from softplc.api.secopts import add_run_options
from softplc.cli.argtypes import count as _count
from softplc.cli.argtypes import duration as _duration
from softplc.cli.argtypes import endpoint as _endpoint
from softplc.cli.argtypes import timeout as _timeout
from softplc.sparkplug.options import add_options as add_sparkplug_options


def cmd_run(args: argparse.Namespace) -> int:
    from softplc.runtime.supervise.runcmd import run
    from softplc.sparkplug.options import from_args as sparkplug_config

    try:  # the whole edge node configuration, before anything starts (docs/sparkplug.md)
        args.sparkplug = sparkplug_config(args)
    except ValueError as exc:
        print(f"softplc run: {exc}", file=sys.stderr)
        return 2
    return run(args)


def add_run(run: argparse.ArgumentParser) -> None:
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
    add_sparkplug_options(run)  # --sparkplug URL and its options (docs/sparkplug.md)
    add_run_options(run)  # --tls, --tls-cert, --tls-key, --trusted-keys (docs/security.md)
    run.set_defaults(func=cmd_run)
