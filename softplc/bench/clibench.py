"""How fast the CLI answers: `softplc status --json` against a running PLC, `softplc --help`
and `softplc --version`, each paired with the same venv's bare `python -c pass` in the same
run (issue 40: at most 5x the bare interpreter); and, for each, what does not depend on the
machine's load: the number of modules imported and the `-X importtime` total.

Owns: the `cli` section of `softplc bench`. Does not know: what the commands import.
"""

from __future__ import annotations

import compileall
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.bench.live import ROOT, end_run, free_port
from softplc.bench.measure import Progress, figures


def _softplc() -> list[str]:
    """The venv's console script, as a person types it; else the module."""
    script = Path(sys.executable).with_name("softplc")
    return [str(script)] if script.exists() else [sys.executable, "-m", "softplc.cli"]


def _wall_ms(argv: list[str]) -> float:
    began = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                          timeout=60, check=False)
    took = (time.perf_counter() - began) * 1000
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)}: exit {done.returncode}: {done.stderr!r}")
    return took


def _start_plc(state: str) -> tuple[subprocess.Popen[bytes], str]:
    url = f"http://127.0.0.1:{free_port()}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--quiet", "--modbus", "off", "--opcua", "off", "--api", url.removeprefix("http://"),
         "--state-dir", state], cwd=ROOT, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL, start_new_session=True)
    api, deadline = ApiClient(url, timeout_s=2), time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if api.status()["state"] == "RUNNING":
                return proc, url
        except (ApiError, ApiUnreachable):
            pass
        time.sleep(0.05)
    end_run(proc)
    raise RuntimeError("softplc run did not answer RUNNING within 60 s")


def _imports(argv: list[str], times: int) -> dict[str, float]:
    """Modules imported and the sum of `-X importtime`'s self times (ms, the least of `times`:
    load only ever adds to it)."""
    # the console script is a Python file: `python -X importtime SCRIPT ARGS`
    command = [sys.executable, "-X", "importtime",
               *(argv[1:] if argv[0] == sys.executable else argv)]
    runs: list[tuple[int, float]] = []
    for _ in range(times):
        done = subprocess.run(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              timeout=60, check=False, text=True)
        rows = [line.split("|")[0].split(":")[1] for line in done.stderr.splitlines()
                if line.startswith("import time:") and "self [us]" not in line]
        runs.append((len(rows), sum(int(us) for us in rows) / 1000))
    return {"modules": runs[-1][0],
            "importtime_ms": round(min(t for _, t in runs), 1)}


def _summary(samples: list[float]) -> dict[str, float]:
    got = figures(samples)
    return {"median_ms": round(got.median, 1), "p99_ms": round(got.p99, 1),
            "max_ms": round(got.max, 1)}


def run(quick: bool, progress: Progress, runs: int | None = None) -> dict[str, Any]:
    runs = runs or (10 if quick else 30)
    # Measured as installed: bytecode compiled (PYTHONDONTWRITEBYTECODE may be set here,
    # and a first run would otherwise pay for compiling every module it imports).
    compileall.compile_dir(str(ROOT / "softplc"), quiet=1)
    state = tempfile.mkdtemp(prefix="softplc-cli-bench-")
    proc, url = _start_plc(state)
    commands = {"bare": [sys.executable, "-c", "pass"],
                "help": [*_softplc(), "--help"],
                "version": [*_softplc(), "--version"],
                "status_json": [*_softplc(), "status", "--json", "--api", url]}
    samples: dict[str, list[float]] = {name: [] for name in commands}
    try:
        for argv in commands.values():  # one unmeasured warm-up each: the page cache
            _wall_ms(argv)
        for k in range(runs):  # interleaved: a change of load hits all three alike
            progress(f"cli: run {k + 1}/{runs}")
            for name, argv in commands.items():
                samples[name].append(_wall_ms(argv))
        imports = {name: _imports(argv, 5 if quick else 10) for name, argv in commands.items()}
    finally:
        end_run(proc)
        shutil.rmtree(state, ignore_errors=True)
    shown = {name: _summary(values) for name, values in samples.items()}
    bare = shown["bare"]["median_ms"]
    return {
        "runs": runs, "bytecode": "compiled (compileall)", "load_average": os.getloadavg(),
        "command": " ".join(Path(a).name if i == 0 else a
                            for i, a in enumerate(commands["status_json"])),
        **{f"{name}_{key}": value for name, got in shown.items() for key, value in got.items()},
        **{f"{name}_{key}": value for name, got in imports.items() for key, value in got.items()},
        "help_over_bare": round(shown["help"]["median_ms"] / bare, 2),
        "version_over_bare": round(shown["version"]["median_ms"] / bare, 2),
        "status_json_over_bare": round(shown["status_json"]["median_ms"] / bare, 2),
    }
