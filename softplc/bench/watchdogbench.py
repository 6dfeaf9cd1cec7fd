"""A busy host is not a stuck PLC: an idle transport PLC (`softplc run programs/transport.yaml
--plant transport --start`, default limits) beside CPU-burning processes on the same cores,
for a while; every fault counts as spurious (the program causes none), with the stalls, the
longest cycle and the lateness.

Owns: the `watchdog` section of `softplc bench` and `python -m softplc.bench.watchdogbench`
(any duration, any `softplc run` options). Does not know: how the loop judges a cycle.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.bench.live import ROOT, free_port
from softplc.bench.measure import Progress
from softplc.core.units import parse_duration_ns

BURNERS = 4  # busy loops: at 2 cores, a load of about 4 beside the PLC's own processes
FULL_S = 1800.0
QUICK_S = 180.0
POLL_S = 1.0  # status every second: its 1000-scan window (10 s at 10 ms) overlaps the last


def _burners(count: int) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(count)]


def _status(api: ApiClient) -> dict[str, Any] | None:
    try:
        return api.status()
    except (ApiError, ApiUnreachable, OSError):
        return None  # a busy host may miss one poll; the next one sees the same window


class _Tally:
    """What the status polls saw: faults, stalls, the worst windows."""

    def __init__(self) -> None:
        self.faults: list[dict[str, Any]] = []
        self.exec_max_us = 0.0
        self.gap_max_us = 0
        self.late_max_us = 0.0
        self.p99_late_us: list[float] = []
        self.scans = 0
        self.stalls = 0
        self.overruns = 0

    def take(self, status: dict[str, Any], api: ApiClient, began: float) -> None:
        timing = status.get("timing", {})
        self.exec_max_us = max(self.exec_max_us, float(timing.get("exec_max_us", 0)))
        self.late_max_us = max(self.late_max_us, float(timing.get("lateness_max_us", 0)))
        self.p99_late_us.append(float(timing.get("lateness_p99_us", 0)))
        self.scans = int(status.get("scan_count", 0))
        self.stalls, self.overruns = int(timing.get("stalls", 0)), int(timing.get("overruns", 0))
        self.gap_max_us = max(self.gap_max_us, int(timing.get("longest_gap_us", 0)))
        # Watchdog and stall faults last until a reset: a poll a second sees every one.
        if status.get("state") == "FAULTED":
            self.faults.append({"after_s": round(time.monotonic() - began, 1),
                                "fault": status.get("fault_name"),
                                "reason": status.get("fault_reason")})
            api.reset()  # count on: every further fault is one more spurious one
            api.start()


def measure(duration_s: float, burners: int = BURNERS, options: Sequence[str] = (),
            progress: Progress | None = None) -> dict[str, Any]:
    """Run the idle PLC for `duration_s` beside `burners` busy loops; `options` are added to
    `softplc run` (none: its defaults, which is what this measures)."""
    modbus, api_port, opcua = free_port(), free_port(), free_port()
    state = tempfile.mkdtemp(prefix="softplc-watchdog-bench-")
    command = [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--plant",
               "transport", "--start", "--quiet", "--modbus", f"127.0.0.1:{modbus}", "--api",
               f"127.0.0.1:{api_port}", "--opcua", f"127.0.0.1:{opcua}", "--state-dir", state,
               *options]
    proc = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    api = ApiClient(f"http://127.0.0.1:{api_port}", timeout_s=5)
    tally, load = _Tally(), []
    try:
        _wait_running(api, proc)
        load = _burners(burners)
        began = said = time.monotonic()
        while (elapsed := time.monotonic() - began) < duration_s:
            time.sleep(POLL_S)
            if (status := _status(api)) is not None:
                tally.take(status, api, began)
            if progress is not None and time.monotonic() - said >= 30:
                said = time.monotonic()
                progress(f"watchdog: {elapsed:.0f}/{duration_s:.0f} s, "
                         f"{len(tally.faults)} fault(s)")
        load_avg = list(os.getloadavg())
    finally:
        for burner in load:
            burner.kill()
            burner.wait()
        _end(proc)
        shutil.rmtree(state, ignore_errors=True)
    late = sorted(tally.p99_late_us)
    return {
        "duration_s": duration_s, "burners": burners, "options": list(options),
        "load_average_end": load_avg, "scans": tally.scans,
        "spurious_faults": len(tally.faults), "faults": tally.faults,
        "stalls": tally.stalls, "overruns": tally.overruns,
        "longest_cycle_ms": round(tally.exec_max_us / 1000, 1),
        "max_lateness_ms": round(max(tally.late_max_us, tally.gap_max_us) / 1000, 1),
        "p99_lateness_ms_median_window": round(late[len(late) // 2] / 1000, 2) if late else None,
        "p99_lateness_ms_worst_window": round(late[-1] / 1000, 2) if late else None,
        "command": "softplc run programs/transport.yaml --plant transport --start "
                   + " ".join(options),
    }


def _wait_running(api: ApiClient, proc: subprocess.Popen[bytes]) -> None:
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"softplc run exited ({proc.returncode}) at start")
        status = _status(api)
        if status is not None and status.get("state") == "RUNNING" and not status.get("stale"):
            return
        time.sleep(0.1)
    raise RuntimeError("the PLC was not RUNNING within 60 s")


def _end(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run(quick: bool, progress: Progress) -> dict[str, Any]:
    return measure(QUICK_S if quick else FULL_S, progress=progress)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softplc.bench.watchdogbench",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--duration", default="30min", help="e.g. 5min (default: 30min)")
    parser.add_argument("--burners", type=int, default=BURNERS,
                        help=f"busy loops beside the PLC (default: {BURNERS})")
    parser.add_argument("options", nargs=argparse.REMAINDER,
                        help="after --: options for softplc run (default: none, its defaults)")
    args = parser.parse_args(argv)
    options = [o for o in args.options if o != "--"]
    result = measure(parse_duration_ns(args.duration) / 1e9, args.burners, options,
                     Progress(False))
    print(json.dumps(result, indent=1))
    return 0 if result["spurious_faults"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
