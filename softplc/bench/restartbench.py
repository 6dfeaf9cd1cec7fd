"""Restarts under load: the scan process of a real `softplc run` killed with SIGKILL again and
again while four Modbus clients poll it; how long until the API answers for the restarted
PLC, whether every restart was warm, and how far the plant's delivered count went back (the
retain interval bounds it: the simulated plant is restored with the snapshot).

Owns: the `restart` section of `softplc bench`. Does not know: how the supervisor heals.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

from pymodbus.client import ModbusTcpClient

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.bench.live import ROOT, end_run
from softplc.bench.measure import Progress, figures

CLIENTS = 4
# The supervisor restarts at most 5 times in 60 s (then gives up, as it should in a crash
# loop) and backs off after restarts within 10 s: kills this far apart measure a restart.
SPACING_S = 12.5


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _poll(port: int, stop: threading.Event, counts: list[int], index: int) -> None:
    """One HMI: FC3 x 100 registers in a loop, reconnecting when the slave drops it."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=1, retries=0)
    while not stop.is_set():
        try:
            if not client.connected and not client.connect():  # type: ignore[no-untyped-call]
                time.sleep(0.05)
                continue
            client.read_holding_registers(0, count=100)
            counts[index] += 1
        except Exception:  # the load must go on whatever one request does
            client.close()  # type: ignore[no-untyped-call]
            time.sleep(0.05)
    client.close()  # type: ignore[no-untyped-call]


def _status(api: ApiClient) -> dict[str, Any] | None:
    try:
        return api.status()
    except (ApiError, ApiUnreachable):
        return None


def _wait(api: ApiClient, ok: Any, timeout_s: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = _status(api)
        if status is not None and ok(status):
            return status
        time.sleep(0.01)
    raise RuntimeError(f"the PLC did not come back within {timeout_s} s")


def _delivered(api: ApiClient) -> int:
    try:
        return int(api.read_symbol("parts_delivered"))
    except (ApiError, ApiUnreachable):
        return -1


def run(quick: bool, progress: Progress, kills: int | None = None) -> dict[str, Any]:
    kills = kills or (3 if quick else 20)
    modbus, api_port = _port(), _port()
    state = tempfile.mkdtemp(prefix="softplc-restart-bench-")
    proc = subprocess.Popen(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--quiet", "--modbus", f"127.0.0.1:{modbus}", "--api", f"127.0.0.1:{api_port}",
         "--opcua", "off", "--state-dir", state, "--retain-interval", "1s"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    api = ApiClient(f"http://127.0.0.1:{api_port}", timeout_s=2)
    stop, counts = threading.Event(), [0] * CLIENTS
    pollers = [threading.Thread(target=_poll, args=(modbus, stop, counts, i), daemon=True)
               for i in range(CLIENTS)]
    restarts: list[dict[str, Any]] = []
    last_kill = 0.0
    try:
        _wait(api, lambda s: s["state"] == "RUNNING" and not s["stale"], 60)
        for poller in pollers:
            poller.start()
        for k in range(kills):
            # At least 1.5 s of scans since the last start: a snapshot of this run exists.
            base = _wait(api, lambda s, k=k: s.get("restarts") == k and not s["stale"], 30)
            _wait(api, lambda s, b=base: s["scan_count"] > b["scan_count"] + 150, 30)
            while restarts and time.monotonic() - last_kill < SPACING_S:
                time.sleep(0.05)
            before = _delivered(api)
            pid = int(_wait(api, lambda s: bool(s.get("scan_pid")), 5)["scan_pid"])
            progress(f"restart: kill -9 of the scan process ({k + 1}/{kills})")
            killed = last_kill = time.monotonic()
            os.kill(pid, signal.SIGKILL)
            after = _wait(api, lambda s, n=k + 1: s.get("restarts") == n and not s["stale"], 30)
            answered = time.monotonic() - killed
            restarts.append({"answered_s": round(answered, 3), "mode": after["start_mode"],
                             "state": after["state"], "delivered_before": before,
                             "delivered_after": _delivered(api)})
    finally:
        stop.set()
        end_run(proc)
    times = figures([r["answered_s"] for r in restarts])
    rollback = [max(r["delivered_before"] - r["delivered_after"], 0) for r in restarts]
    return {
        "kills": kills, "modbus_clients": CLIENTS, "modbus_requests": sum(counts),
        "restarts": restarts, "answered_median_s": times.median, "answered_max_s": times.max,
        "all_warm": all(r["mode"] == "warm" and r["state"] == "RUNNING" for r in restarts),
        "delivered_rollback_max": max(rollback, default=0),
        "retain_interval_s": 1.0, "spacing_s": SPACING_S,
    }
