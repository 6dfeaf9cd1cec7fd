"""`softplc bench`: run the benchmark sections, write JSON, plots and BENCHMARKS.md.

Owns: which sections run in which mode, the headline keys that runs are compared by (dotted
names such as `engine.vs_snakes_1k`), the targets they are reported against, and the machine
description. Every headline figure is a ratio against a baseline measured in the same run.
Does not know: how a section measures (engine.py, scanbench.py, modbusbench.py, ...).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import json
import os
import platform
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from softplc.bench.markdown import REPORTED
from softplc.bench.measure import Progress

SECTIONS = ("engine", "scan", "simulate", "modbus", "online_change", "restart", "memory",
            "web", "analysis", "opcua", "isolation", "cli", "startup")
# Run only when named (--only): the watchdog section takes 30 minutes (--quick: 3).
ON_REQUEST = ("watchdog", "sparkplug")  # sparkplug: a fleet on Debian's mosquitto


@dataclass(frozen=True, slots=True)
class Target:
    key: str  # dotted: section.key
    op: str  # ">=", "<=", "=="
    bound: float
    meaning: str
    unit: str = "x"  # "x": a ratio (times); else the unit of a count, e.g. "scans"
    period: str = ""  # the scan period the figure was measured at, "" when there is none

    def met(self, value: float | None) -> bool | None:
        if value is None:
            return None
        if self.op == ">=":
            return value >= self.bound
        if self.op == "<=":
            return value <= self.bound
        return value == self.bound


TARGETS = (
    Target("engine.vs_snakes_1k", ">=", 300, "SNAKES round time / ours, 1,000 transitions"),
    Target(
        "engine.scale_10k_over_10",
        "<=",
        3,
        "our round time at 10,000 / at 10 transitions, same number of firing transitions",
    ),
    Target(
        "scan.p99_ratio_loaded_over_floor_1ms",
        "<=",
        2,
        "p99 lateness at 1 ms, loaded (4 Modbus clients + HTTP poll) / empty-loop floor",
        period="1 ms",
    ),
    Target("scan.exec_over_round", "<=", 2,
           "median scan execution of transport in the live loop / median firing round of the "
           "same net, same run", period="1 ms"),
    Target("simulate.realtime_factor", ">=", 1000,
           "simulated time / wall time of softplc simulate, both case studies (the slower)",
           period="10 ms"),
    Target("scan.overruns_loaded_1ms", "==", 0, "overruns at 1 ms, loaded", "scans", "1 ms"),
    Target(
        "modbus.throughput_ratio_vs_pymodbus_4c",
        ">=",
        0.9,
        "our slave's requests/s / plain pymodbus server's, 4 clients, FC3 x 100 registers",
        period="1 ms",
    ),
    Target(
        "web.p99_ratio_over_floor_1ms",
        "<=",
        2,
        "p99 lateness at 1 ms with 3 operator pages open / empty-loop floor (as loaded Modbus)",
        period="1 ms",
    ),
    Target(
        "opcua.p99_ratio_over_floor_1ms",
        "<=",
        2,
        "p99 lateness at 1 ms with 4 subscribed OPC UA clients / empty-loop floor",
        period="1 ms",
    ),
    Target(
        "online_change.missed_scans",
        "==",
        0,
        "scans missed by an online change (worst of 10 and 10,000 transitions)",
        "scans",
        "1 ms",
    ),
    Target("restart.answered_max_s", "<=", 2,
           "kill -9 of the scan process under 4 Modbus clients: seconds until the API answers "
           "for the restarted PLC (worst of 3 quick / 20 full, 12.5 s apart)", "s", "10 ms"),
    Target("restart.all_warm", "==", True, "every restart warm and RUNNING", "", "10 ms"),
    Target("analysis.vs_snakes_states_per_s", ">=", 100,
           "our states/s / SNAKES StateGraph's, same P/T nets (Kanban 2, FMS 2, ...)"),
    Target("analysis.kanban5_s", "<=", 5,
           "full reachability graph of Kanban N = 5 (2,546,432 states), seconds; not in --quick"),
    Target("isolation.modbus_p99_ratio_max", "<=", 2,
           "Modbus p99 response time under the worst OPC UA or HTTP abuse / without abuse",
           period="1 ms"),
    Target("isolation.http_p99_ratio_max", "<=", 2,
           "HTTP /status p99 under the worst OPC UA or HTTP abuse / without abuse",
           period="1 ms"),
    Target("isolation.scan_p99_ratio_max", "<=", 2,
           "scan p99 lateness under the worst OPC UA or HTTP abuse / without abuse",
           period="1 ms"),
    Target("cli.status_json_over_bare", "<=", 5,
           "wall time of `softplc status --json` against a running PLC / the same venv's "
           "`python -c pass`, medians, same run"),
    Target("cli.help_over_bare", "<=", 5,
           "wall time of `softplc --help` / the same venv's `python -c pass`, medians, same run"),
)
HEADLINE = (*(t.key for t in TARGETS), "memory.rss_mb", *(key for key, _, _ in REPORTED))


# Each section's module in softplc/bench (imported when its section runs: some need the
# bench extra, SNAKES or matplotlib).
_MODULES = {"engine": "engine", "scan": "scanbench", "simulate": "simbench",
            "modbus": "modbusbench", "web": "webbench", "opcua": "opcuabench",
            "analysis": "analysisbench", "restart": "restartbench",
            "online_change": "onlinebench", "memory": "memorybench",
            "watchdog": "watchdogbench", "isolation": "isolationbench", "cli": "clibench",
            "startup": "startbench", "sparkplug": "sparkplugbench"}


def _section_runner(name: str) -> Callable[[bool, Progress], dict[str, Any]]:
    module = importlib.import_module(f"softplc.bench.{_MODULES[name]}")
    run: Callable[[bool, Progress], dict[str, Any]] = module.run
    return run


def machine() -> dict[str, Any]:
    """What the figures were measured on: they mean little without it."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    with contextlib.suppress(ValueError, OSError):
        mem_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    versions: dict[str, str | None] = {}
    for package in ("softplc", "numpy", "pymodbus", "aiohttp", "snakes", "matplotlib"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "memory_gb": mem_gb,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "versions": versions,
        "load_average": list(os.getloadavg()),
    }


def lookup(results: dict[str, Any], dotted: str) -> Any:
    section, key = dotted.split(".", 1)
    value = results.get("sections", {}).get(section, {})
    return value.get(key) if isinstance(value, dict) else None


SectionRunner = Callable[[str], Callable[[bool, Progress], dict[str, Any]]]


def run_sections(
    names: list[str], quick: bool, progress: Progress, runner: SectionRunner = _section_runner
) -> dict[str, Any]:
    """Every named section, each timed; a section that fails is recorded, the rest go on."""
    results: dict[str, Any] = {
        "mode": "quick" if quick else "full",
        "machine": machine(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "sections": {},
        "seconds": {},
    }
    for name in names:
        progress(f"{name}: starting")
        began = time.monotonic()
        try:
            results["sections"][name] = runner(name)(quick, progress)
        except Exception as exc:  # a broken section must not lose the others' figures
            results["sections"][name] = {
                "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc(),
            }
            progress(f"{name}: FAILED ({type(exc).__name__}: {exc})")
        results["seconds"][name] = round(time.monotonic() - began, 1)
    results["machine"]["load_average_end"] = list(os.getloadavg())
    results["headline"] = {key: lookup(results, key) for key in HEADLINE}
    results["targets"] = [
        {
            "key": t.key,
            "target": f"{t.op} {t.bound:g}",
            "meaning": t.meaning,
            "unit": t.unit,
            "period": t.period,
            "value": results["headline"][t.key],
            "met": t.met(results["headline"][t.key]),
        }
        for t in TARGETS
    ]
    return results


class _SectionProgress(Progress):
    """Progress for a log (stderr not a terminal): one line per section started or failed,
    not one per step (a terminal gets every step on one line that rewrites itself)."""

    def __call__(self, message: str) -> None:
        if message.endswith(": starting") or "FAILED" in message:
            super().__call__(message)


def _progress(quiet: bool) -> Progress:
    return Progress(quiet) if quiet or sys.stderr.isatty() else _SectionProgress(quiet)


def main(args: argparse.Namespace) -> int:
    names = list(SECTIONS)
    if getattr(args, "only", None):
        names = [n.strip() for n in args.only.split(",") if n.strip()]
        unknown = [n for n in names if n not in SECTIONS + ON_REQUEST]
        if unknown:
            print(
                f"softplc bench: unknown section(s) {', '.join(unknown)}; "
                f"expected some of {', '.join(SECTIONS + ON_REQUEST)}",
                file=sys.stderr,
            )
            return 2
    progress = _progress(getattr(args, "quiet", False))
    results = run_sections(names, args.quick, progress)
    results["command"] = (
        "softplc bench"
        + (" --quick" if args.quick else "")
        + (f" --only {','.join(names)}" if names != list(SECTIONS) else "")
    )
    progress.done()
    if args.plots:
        from softplc.bench.report import write_plots

        results["plots"] = write_plots(results, Path(args.plots))
    if args.json_file:
        Path(args.json_file).write_text(json.dumps(results, indent=1, default=str) + "\n")
    if getattr(args, "markdown", None):
        from softplc.bench.report import write_markdown

        write_markdown(results, Path(args.markdown))
    from softplc.bench.report import summary

    print(summary(results, written=[p for p in (args.json_file, getattr(args, "markdown", None))
                                    if p]))
    failed = [n for n, s in results["sections"].items() if "error" in s]
    if failed:
        print(f"softplc bench: section(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0
