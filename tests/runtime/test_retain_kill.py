"""kill -9 at 50 random moments of a simulated production run (issue 7 item 1).

The scan process is the real ScanLoop with retain on (state dir, 2 s interval of scan time),
forked from this test so that a restart costs milliseconds, not a numpy import. It runs the
transport program on the sim transport plant on a virtual clock (scans back to back, time
advancing one period per scan), so each real second is about a minute of production and the
plant physics cannot be upset by a loaded machine. Seeded kill delays of 0.05-0.5 s.

What "nothing lost or done twice" means here. The sim plant lives in the scan process and
dies with it, so its state is retained too, as the field side of the snapshot (labelled
simulation-only): a restart rolls the PLC and the plant back together to the snapshot. So:
  - every restart is warm and loads exactly the newest snapshot on disk whose checksum holds
    (checked here independently of retain.py), even when the kill hit a write;
  - at every restart the PLC and the plant agree: the net's delivered count (coloured token)
    == the %QW0 counter it writes == the parts the plant saw taken off; the plant has no
    fault (a PLC whose marking did not match the belt would collide parts or push one off);
  - what is lost is only what ran after that snapshot: the restored scan count and part
    count never exceed those reached before the kill (nothing done twice), and the parts
    lost fit into the scans lost (at most one per arrival gap);
  - production goes on across the kills, and a clean stop at the end leaves a snapshot of
    the very last scan.
"""

from __future__ import annotations

import base64
import hashlib
import json
import multiprocessing as mp
import os
import random
import signal
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from softplc.devices.plants.transport import TransportConfig
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop

ROOT = Path(__file__).resolve().parents[2]
PERIOD_NS = 10_000_000
INTERVAL_NS = 2_000_000_000
KILLS = 50
GAP_MIN_NS = TransportConfig().gap_min_ns


def _counts(loop: ScanLoop) -> dict[str, Any]:
    plc = loop.runner.plc
    assert plc.net is not None and plc.engine is not None
    (token,) = plc.engine.state.tokens[plc.net.place_index["delivered"]]
    (driver,) = loop.runner.drivers
    report = driver.plant.report()  # type: ignore[attr-defined]
    return {"scan_count": plc.scan_count, "state": plc.state.name, "delivered": token["count"],
            "qw0": int(plc.image.qw[0]), "parts_out": report.parts_out,
            "faults": list(report.faults)}


def _production(state_dir: str, conn: Connection, progress: Any, stop: Any) -> None:
    loop = ScanLoop(LoopConfig(program=str(ROOT / "programs/transport.yaml"), start=True,
                               period_ns=PERIOD_NS, state_dir=state_dir,
                               retain_interval_ns=INTERVAL_NS), None, None, VirtualClock())
    counts = _counts(loop) if loop.start_mode == "warm" else {"scan_count": 0, "parts_out": 0}
    conn.send({"mode": loop.start_mode, "reason": loop.start_reason, **counts})

    step = loop.runner.step

    def step_and_record(*args: Any, **kwargs: Any) -> Any:
        """What the run reached, recorded after every scan and before its retain capture."""
        result = step(*args, **kwargs)
        if not loop.runner.drivers:
            return result  # the first scan downloads; its devices open after it
        c = _counts(loop)
        progress[0], progress[1] = c["scan_count"], c["parts_out"]
        return result

    loop.runner.step = step_and_record  # type: ignore[method-assign]
    loop.run(stop)
    conn.send(_counts(loop))


def newest_valid(state: Path) -> tuple[str, dict[str, Any]] | None:
    """The test's own reading of the state dir: newest retain-*.json whose sha256 holds."""
    for path in sorted(state.glob("retain-*.json"), reverse=True):
        try:
            data = path.read_bytes()
        except FileNotFoundError:  # rotated away by the writer since the listing
            continue
        head, _, body = data.partition(b"\n")
        try:
            header = json.loads(head)
        except ValueError:
            continue
        if header.get("sha256") == hashlib.sha256(body).hexdigest():
            return path.name, json.loads(body)
    return None


def test_kill_9_at_50_random_moments_loses_nothing_beyond_the_snapshot(tmp_path: Path) -> None:
    state = tmp_path / "state"
    ctx = mp.get_context("fork")
    progress = ctx.RawArray("q", 2)
    rng = random.Random(20240607)
    restored: list[dict[str, Any]] = []
    lost_scans: list[int] = []
    torn = 0
    killed_at = (0, 0)  # scan count and parts out the killed run had reached
    began = time.monotonic()
    for run in range(KILLS + 1):
        expected = newest_valid(state)
        torn += len(list(state.glob(".retain-*.tmp")))
        parent, child = ctx.Pipe()
        stop = ctx.Event()
        proc = ctx.Process(target=_production, args=(str(state), child, progress, stop))
        proc.start()
        try:
            assert parent.poll(60) or proc.exitcode is None, f"scan process exit {proc.exitcode}"
            assert parent.poll(0), "the scan process did not start"
            start = parent.recv()
            if run == 0:
                assert start["mode"] == "cold" and "no snapshot" in start["reason"]
                deadline = time.monotonic() + 30
                while newest_valid(state) is None:  # let the first snapshot reach the disk
                    assert time.monotonic() < deadline and proc.is_alive()
                    time.sleep(0.01)
            else:
                assert expected is not None
                name, payload = expected
                assert start["mode"] == "warm", start["reason"]
                assert start["reason"].startswith(f"snapshot {name} "), (start, name)
                assert start["scan_count"] == payload["scan_count"]
                assert start["state"] == "RUNNING"
                assert start["faults"] == []
                assert start["delivered"] == start["qw0"] == start["parts_out"], start
                previous = restored[-1]
                assert start["scan_count"] >= previous["scan_count"]
                assert start["parts_out"] >= previous["parts_out"]
                # against what the killed run had reached
                scans_lost = killed_at[0] - start["scan_count"]
                parts_lost = killed_at[1] - start["parts_out"]
                assert scans_lost >= 0 and parts_lost >= 0, (killed_at, start)
                assert parts_lost <= scans_lost * PERIOD_NS // GAP_MIN_NS + 1
                lost_scans.append(scans_lost)
            restored.append(start)
            if run == KILLS:
                time.sleep(0.3)
                stop.set()
                assert parent.poll(60)
                final = parent.recv()
                proc.join(30)
                assert proc.exitcode == 0
                break
            time.sleep(rng.uniform(0.05, 0.5))
            os.kill(proc.pid, signal.SIGKILL)  # type: ignore[arg-type]
            proc.join(30)
            assert proc.exitcode == -signal.SIGKILL
            killed_at = (progress[0], progress[1])
        finally:
            if proc.is_alive():
                proc.kill()
                proc.join(10)
    name, payload = newest_valid(state) or ("", {})
    assert payload["scan_count"] == final["scan_count"]  # on stop: the very last scan
    assert final["faults"] == [] and final["delivered"] == final["parts_out"]
    # retained before the stop drove the outputs safe: the counter word is the program's
    qw = np.frombuffer(base64.b64decode(payload["image"]["qw"]), dtype="<u2")
    assert payload["state"] == "RUNNING" and qw[0] == final["delivered"] and final["qw0"] == 0
    assert final["parts_out"] > restored[1]["parts_out"]  # production went on across kills
    print(f"\n{KILLS} kills in {time.monotonic() - began:.1f} s: {final['parts_out']} parts "
          f"delivered in {final['scan_count']} scans ({final['scan_count'] * PERIOD_NS / 1e9:.0f} s"
          f" of plant time); kills during a write (temp file left) {torn}; scans lost per kill"
          f" max {max(lost_scans)}, mean {sum(lost_scans) / len(lost_scans):.0f} (interval "
          f"{INTERVAL_NS // PERIOD_NS} scans)")
