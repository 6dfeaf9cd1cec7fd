"""The scan count never goes back across a restart of the scan process (issue 26.5).

`softplc run` as real processes; the Modbus status block is polled all along while the scan
process is killed with SIGKILL a third of a retain interval after a snapshot was written, so the
newest snapshot is about 100 scans older than the last scan published. Before the fix the
restarted process went on from the snapshot's count and the status block's count went back
by that much; now it goes on from the count the killed process last published."""

from __future__ import annotations

import itertools
import os
import signal
import threading
import time
from pathlib import Path

from pymodbus.client import ModbusTcpClient

from softplc.hmi.map import STATUS_SCAN_COUNT, STATUS_WORDS
from tests.runtime.test_supervision import ROOT, Run
from tests.support import eventually_reachable

STATUS_BASE = 1024  # input registers: %IW (1024 words by default), then the status block


def _counts(port: int, stop: threading.Event, seen: list[int]) -> None:
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    try:
        while not stop.is_set():
            try:
                words = client.read_input_registers(STATUS_BASE, count=STATUS_WORDS).registers
            except Exception:  # the reader reconnects; a lost poll is not a count
                time.sleep(0.01)
                continue
            high, low = words[STATUS_SCAN_COUNT], words[STATUS_SCAN_COUNT + 1]
            seen.append(high << 16 | low)
            time.sleep(0.003)
    finally:
        client.close()


def test_the_scan_count_goes_on_after_a_killed_scan_process(tmp_path: Path) -> None:
    run = Run(ROOT, "programs/transport.yaml", tmp_path / "state", "--plant", "transport",
              "--retain-interval", "3s")
    seen: list[int] = []
    stop = threading.Event()
    poller = threading.Thread(target=_counts, args=(run.modbus, stop, seen), daemon=True)
    try:
        written = eventually_reachable(lambda: (n := run.status()["retain"]["writes"]) >= 1
                                       and n, 30, "a retain snapshot")
        eventually_reachable(lambda: run.status()["retain"]["writes"] > written, 5,
                             "the next retain snapshot")
        poller.start()
        time.sleep(1.0)  # a third of an interval: about 100 scans that no snapshot holds
        first = run.scan_pid()
        os.kill(first, signal.SIGKILL)
        killed_at = len(seen)
        status = eventually_reachable(
            lambda: (s := run.status()).get("restarts") == 1 and s["state"] == "RUNNING"
            and not s["stale"] and s, 10, "the restart")
        assert status["start_mode"] == "warm" and status["scan_pid"] != first
        after = status["scan_count"]
        eventually_reachable(lambda: len(seen) > killed_at + 20, 5, "polls after the restart")
    finally:
        stop.set()
        run.stop(signal.SIGTERM, timeout_s=10)
        run.kill_group()
    snapshot_scan = int(status["start_reason"].split(" from scan ")[1].split(",")[0])
    assert killed_at > 0 and max(seen[:killed_at]) - snapshot_scan >= 10, \
        "the kill came too soon after a snapshot: nothing to lose"
    drops = [(a, b) for a, b in itertools.pairwise(seen) if b < a]
    assert not drops, f"the scan count went back: {drops[:5]}"
    assert after > max(seen[:killed_at])  # went on from the last scan published
