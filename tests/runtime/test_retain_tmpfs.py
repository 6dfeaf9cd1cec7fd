"""Retain on a really full and a nearly full file system (issue 19 part 2): a small tmpfs
mounted for the test (root only: skipped elsewhere; tests/runtime/test_retain_store.py covers
the same paths through a fault-injecting file layer, everywhere).

Nearly full: the real ScanLoop (forked, virtual clock, retain every 5 scans) runs a program
whose snapshot grows every scan until it no longer fits beside the two kept ones; the status
counts the failed writes; then kill -9, and a new ScanLoop on the same directory starts warm
from the newest complete snapshot. Full: a write to a tmpfs with no byte free fails with
ENOSPC, is counted, leaves no temporary (the old writer left a 0-byte .tmp per failed write)
and the snapshots already there stay loadable.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.retain import writer as retain
from tests.core.helpers import write_io
from tests.runtime.test_retain_store import a_capture

MS = 1_000_000
TAG = "t" * 40
GROWING = f"""program: growing
io_image: io.yaml
places:
  counter: {{tokens: [{{n: 0}}]}}
  pile: {{coloured: true, capacity: 3000}}
transitions:
  gen:
    from: [{{place: counter, var: c}}]
    to:
      - {{place: counter, token: {{n: "c.n + 1"}}}}
      - {{place: pile, token: {{n: "c.n", tag: "'{TAG}'"}}}}
"""


@pytest.fixture
def tmpfs(tmp_path: Path) -> Iterator[Path]:
    """A 128 KiB tmpfs at tmp_path/fs, unmounted afterwards."""
    mount = tmp_path / "fs"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (the fault-injecting tests cover the logic)")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=128k,mode=0700", "tmpfs",
                           str(mount)], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def config(program: Path, state: Path) -> LoopConfig:
    return LoopConfig(program=str(program), start=True, period_ns=10 * MS,
                      state_dir=str(state), retain_interval_ns=50 * MS)


def _child(program: Path, state: Path, report: Path) -> None:
    """The scan process: the real loop, its retain info reported every 20 ms (outside the
    tmpfs) until it is killed."""
    # The real clock at 1 ms (not a virtual one): the pile grows one record per scan, so the
    # retain writer gets several snapshots on disk before the disk fills, whatever the speed
    # of the machine; supervision relaxed, a loaded machine must not fault the PLC (a faulted
    # net stops growing and the disk would never fill).
    loop = ScanLoop(dataclasses.replace(config(program, state), period_ns=MS, watchdog=1000.0,
                                        on_stall="continue"), None, None)

    def reporter() -> None:
        while True:
            assert loop.retain is not None
            info = dict(loop.retain.info(), scans=loop.runner.plc.scan_count)
            (report.parent / "report.tmp").write_text(json.dumps(info))
            os.replace(report.parent / "report.tmp", report)
            time.sleep(0.02)

    threading.Thread(target=reporter, daemon=True).start()
    loop.run()


def _wait_report(report: Path, proc: Any, ready: Any, timeout_s: float) -> dict[str, Any]:
    deadline = time.monotonic() + timeout_s
    info: dict[str, Any] = {}
    while time.monotonic() < deadline and proc.is_alive():
        if report.exists():
            info = json.loads(report.read_text())
            if ready(info):
                return info
        time.sleep(0.05)
    raise AssertionError(f"the scan process did not get there: {info}")


def newest_valid(state: Path) -> tuple[str, dict[str, Any]]:
    """The newest snapshot whose header and checksum hold, read independently of the store."""
    for path in sorted(state.glob("retain-*.json"), reverse=True):
        try:
            return path.name, retain.from_bytes(path.read_bytes())
        except retain.SnapshotInvalid:
            continue
    raise AssertionError(f"no valid snapshot in {state}")


def test_kill_9_after_the_disk_filled_up_restarts_warm_from_the_newest_complete_snapshot(
        tmp_path: Path, tmpfs: Path) -> None:
    write_io(tmp_path)
    program = tmp_path / "growing.yaml"
    program.write_text(GROWING, encoding="utf-8")
    state, report = tmpfs / "state", tmp_path / "report.json"
    proc = mp.get_context("fork").Process(target=_child, args=(program, state, report))
    proc.start()
    try:
        # The pile stops growing at 3000 records (~190 KB of snapshot): long before that, a
        # snapshot no longer fits beside the two kept ones in 128 KiB.
        info = _wait_report(report, proc, lambda i: i["errors"] >= 5 and i["scans"] > 3200,
                            timeout_s=90)
    finally:
        if proc.pid is not None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.join(10)
    assert info["writes"] >= 3 and info["errors_by_stage"]["write"] >= 5, info
    assert "ENOSPC" in info["last_error"] and info["consecutive_errors"] >= 5, info
    assert info["temps_removed"] >= info["errors"] - 1, info  # each failure cleaned up
    name, snap = newest_valid(state)
    on_disk = sorted(p.name for p in state.iterdir())
    assert name == info["last"], (info, on_disk)  # no later write replaced it on disk
    assert len(list(state.glob("retain-*.json"))) == 2, (info, on_disk)

    loop = ScanLoop(config(program, state), None, None, VirtualClock(0))
    try:
        assert loop.start_mode == "warm", loop.start_reason
        assert loop.start_reason.startswith(f"snapshot {name} from scan {snap['scan_count']}")
        assert loop.runner.plc.scan_count == snap["scan_count"]
        assert loop.document()["retain"]["temps_removed"] <= 1  # a kill inside a write: one
    finally:
        loop.shutdown()
    final = None if loop.retain is None else loop.retain.final
    assert final is not None
    assert [p for p in state.iterdir() if p.name.endswith(".tmp")] == []
    # The restored state is the smaller one of the last good snapshot: its final snapshot may
    # fit again (then it is the newest valid file), or fail on the full disk (then the one
    # restored from is still the newest).
    if final.written:
        assert newest_valid(state)[0] == final.path
    else:
        assert "ENOSPC" in final.error and newest_valid(state)[0] == name


def test_a_completely_full_disk_fails_every_write_cleanly(tmp_path: Path, tmpfs: Path) -> None:
    store = retain.RetainStore.open(tmpfs / "state")
    for seq in (1, 2):
        store.write({"seq": seq, "program_hash": "h", "fill": "x" * 8000})
    filler = tmpfs / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT, 0o600)
    try:  # take every byte left
        while os.write(fd, b"\0" * 4096) > 0:
            pass
    except OSError:
        pass
    finally:
        os.close(fd)
    assert os.statvfs(tmpfs).f_bavail == 0
    failures = []
    for _ in range(5):
        try:
            store.write({"seq": store.seq + 1, "program_hash": "h", "fill": "y" * 100})
        except retain.WriteFailed as exc:
            failures.append(exc)
    writer = retain.RetainWriter(store)
    writer.submit(a_capture(tmp_path))
    final = writer.stop(a_capture(tmp_path))
    assert not final.written and "ENOSPC" in final.error
    assert writer.info()["errors_by_stage"]["write"] >= 1
    assert len(failures) == 5 and all(f.stage is retain.Stage.WRITE for f in failures)
    assert all("ENOSPC" in str(f) for f in failures)
    assert [p.name for p in (tmpfs / "state").iterdir() if p.name.endswith(".tmp")] == []
    again = retain.RetainStore.open(tmpfs / "state")
    loaded, skipped = again.load_newest()
    assert loaded is not None and loaded.payload["seq"] == 2 and skipped == []
    again.close()
