"""How long `softplc run` takes to start (issue 40 item 2): from the command to the first scan
and to `/healthz` answering, for the transport program and for a 10,000-transition ring
(bench/netgen.py), medians of a few runs each. With SOFTPLC_BENCH_BEFORE=<another checkout>,
the same commands run from that checkout too, interleaved with these, in the same run: a
before/after of a change under the same load.

The first scan: the moment the status, read right after /healthz answers, puts it at (`now -
scan_count x period`, the same for both checkouts: an older one does not say when its loop
began; 10 ms period, a skipped slot makes it look earlier). The scan process's own time of
its loop's start (status `start_program.loop_ns`, one period before the first scan) is kept
beside it where it is shown.

Owns: the `startup` section of `softplc bench`. Does not know: how a start compiles.
"""

from __future__ import annotations

import compileall
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from softplc.bench import netgen
from softplc.bench.live import ROOT, end_run, free_port
from softplc.bench.measure import Progress, figures

PERIOD_MS = 10
BIG = 10_000  # transitions of the big start program


def _programs(tmp: Path) -> dict[str, Path]:
    """transport.yaml as shipped, and a 10,000-transition ring on transport's io image."""
    (tmp / "programs").mkdir()
    shutil.copytree(ROOT / "io_images", tmp / "io_images")
    ring = tmp / "programs" / "ring10k.yaml"
    ring.write_text(netgen.to_yaml(netgen.ring(BIG), "../io_images/transport.yaml"),
                    encoding="utf-8")
    return {"transport": ROOT / "programs" / "transport.yaml", "ring_10k": ring}


def _get(url: str) -> dict[str, Any] | None:
    try:
        with urllib.request.urlopen(url, timeout=2) as reply:  # loopback only
            result: dict[str, Any] = json.loads(reply.read())
            return result
    except (urllib.error.URLError, OSError, ValueError):
        return None


def once(checkout: Path, program: Path, state: str, timeout_s: float = 180.0) -> dict[str, Any]:
    """One `softplc run` of `program` from `checkout`: milliseconds from the command to the
    first scan and to /healthz; the scan process's own account of its start (status)."""
    port = free_port()
    argv = [sys.executable, "-m", "softplc.cli", "run", str(program), "--start", "--quiet",
            "--modbus", "off", "--opcua", "off", "--api", f"127.0.0.1:{port}",
            "--state-dir", state, "--period", f"{PERIOD_MS}ms"]
    env = {**os.environ, "PYTHONPATH": str(checkout)}
    began = time.monotonic_ns()
    proc = subprocess.Popen(argv, cwd=checkout, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        deadline = time.monotonic() + timeout_s
        while _get(f"http://127.0.0.1:{port}/healthz") is None:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"softplc run {program.name} from {checkout} did not "
                                   f"answer /healthz (exit {proc.poll()})")
            time.sleep(0.005)
        healthz = time.monotonic_ns()
        status = _get(f"http://127.0.0.1:{port}/api/v1/status") or {}
        read = time.monotonic_ns()
    finally:
        end_run(proc)
    first = read - int(status.get("scan_count", 0)) * PERIOD_MS * 1_000_000
    start = status.get("start_program") or {}
    out = {"healthz_ms": (healthz - began) / 1e6, "first_scan_ms": (first - began) / 1e6,
           "compiled_by": start.get("compiled_by", "scan process (before start_program)")}
    if start.get("loop_ns"):
        out["loop_ms"] = (start["loop_ns"] - began) / 1e6
    return out


def _median(samples: list[dict[str, Any]], key: str) -> float | None:
    values = [s[key] for s in samples if key in s]
    return round(figures(values).median, 1) if values else None


def run(quick: bool, progress: Progress, runs: int | None = None) -> dict[str, Any]:
    runs = runs or (3 if quick else 7)
    before = os.environ.get("SOFTPLC_BENCH_BEFORE")
    checkouts = {"after": ROOT, **({"before": Path(before).resolve()} if before else {})}
    for checkout in checkouts.values():  # as installed: bytecode compiled (the scan process's
        compileall.compile_dir(str(checkout / "softplc"), quiet=1)  # spawn runs with -B)
    tmp = Path(tempfile.mkdtemp(prefix="softplc-start-bench-"))
    samples: dict[str, list[dict[str, Any]]] = {}
    try:
        programs = _programs(tmp)
        for k in range(runs):  # interleaved: a change of load hits every variant alike
            for name, program in programs.items():
                for which, checkout in checkouts.items():
                    state = tempfile.mkdtemp(dir=tmp)
                    got = once(checkout, program, state)
                    samples.setdefault(f"{name}_{which}", []).append(got)
                    progress(f"startup {name} {which} {k + 1}/{runs}: healthz "
                             f"{got['healthz_ms']:.0f} ms, first scan "
                             f"{got['first_scan_ms']:.0f} ms ({got['compiled_by']})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    out: dict[str, Any] = {"runs": runs, "period_ms": PERIOD_MS, "big_transitions": BIG,
                           "load_average": list(os.getloadavg()),
                           "command": "softplc bench --only startup"
                           + (f" (SOFTPLC_BENCH_BEFORE={before})" if before else "")}
    for variant, seen in samples.items():
        name, which = variant.rsplit("_", 1)
        prefix = name if which == "after" else f"{name}_before"
        out[f"{prefix}_first_scan_ms"] = _median(seen, "first_scan_ms")
        out[f"{prefix}_healthz_ms"] = _median(seen, "healthz_ms")
        if which == "after":
            out[f"{prefix}_loop_ms"] = _median(seen, "loop_ms")
            out[f"{prefix}_compiled_by"] = seen[-1]["compiled_by"]
    return out
