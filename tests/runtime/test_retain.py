"""Retain and warm restart (issue 7 item 1): the snapshot file, the start decision, the scan
loop writing at its interval and on stop, restoring marking, timers and %M, the state lock.

In process on a virtual clock, except the last tests, which run `softplc run` for real.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.retain import writer as retain
from softplc.runtime.retain.writer import RetainStore, SnapshotInvalid, StateDirBusy
from tests.core.helpers import write_io

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000
TIMED = """program: timed
io_image: io.yaml
places:
  p: {tokens: 1, outputs: [r]}
  x: {outputs: {qw: 9}}
  d: {tokens: 1}
  e: {}
transitions:
  wait: {from: [p], to: [x], delay: 500ms}
  work: {from: [d], to: [e], duration: 400ms, outputs: [m]}
"""


def timed_program(directory: Path, body: str = TIMED) -> str:
    write_io(directory)
    path = directory / "timed.yaml"
    path.write_text(body, encoding="utf-8")
    return str(path)


def make_loop(program: str, state: Path, scans: int, clock_ns: int = 0, start: bool = True,
              interval_ns: int = 0, warm_start: str = "run",
              trace: Path | None = None) -> ScanLoop:
    config = LoopConfig(program=program, start=start, period_ns=10 * MS, max_scans=scans,
                        state_dir=str(state), retain_interval_ns=interval_ns,
                        warm_start=warm_start, trace=str(trace) if trace else None)
    return ScanLoop(config, None, None, VirtualClock(clock_ns))


def trace_times(path: Path) -> dict[str, int]:
    """transition -> scan time (ns) of its first firing or completion in a trace."""
    seen: dict[str, int] = {}
    for line in path.read_text().splitlines():
        record = json.loads(line)
        for name in record.get("fired", []) + [f"{n} done" for n in record.get("done", [])]:
            seen.setdefault(name, record["t"])
    return seen


# -- the file ---------------------------------------------------------------------------------

def test_a_snapshot_file_is_complete_and_checksummed(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    make_loop(program, tmp_path / "state", scans=3).run()
    files = list((tmp_path / "state").glob("retain-*.json"))
    assert len(files) == 1  # interval 0: written on stop only
    data = files[0].read_bytes()
    header = json.loads(data.partition(b"\n")[0])
    assert header["format"] == retain.FORMAT and len(header["sha256"]) == 64
    payload = retain.from_bytes(data)
    assert payload["program"] == "timed" and payload["scan_count"] == 3
    assert payload["program_hash"] == compile_file(program).program_hash
    flipped = bytearray(data)
    flipped[-5] ^= 0x01
    with pytest.raises(SnapshotInvalid, match="checksum mismatch"):
        retain.from_bytes(bytes(flipped))
    with pytest.raises(SnapshotInvalid, match="partial"):
        retain.from_bytes(data[: len(data) // 2])
    with pytest.raises(SnapshotInvalid, match="partial"):
        retain.from_bytes(data[:10])
    assert not list((tmp_path / "state").glob(".*.tmp"))


def test_a_corrupt_newest_snapshot_falls_back_to_the_older_one_then_cold(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    state = tmp_path / "state"
    make_loop(program, state, scans=3).run()
    make_loop(program, state, scans=8).run()  # warm: 3 -> 8 scans, a second file
    older, newest = sorted(state.glob("retain-*.json"))
    newest.write_bytes(newest.read_bytes()[:-7])  # torn: as a crash in a non-atomic write
    loop = make_loop(program, state, scans=9)
    assert loop.start_mode == "warm" and older.name in loop.start_reason
    assert "skipped" in loop.start_reason and "partial" in loop.start_reason
    assert loop.runner.plc.scan_count == 3
    loop.retain.close()  # type: ignore[union-attr]
    for path in state.glob("retain-*.json"):
        data = bytearray(path.read_bytes())
        data[-3] ^= 0x20
        path.write_bytes(bytes(data))
    loop = make_loop(program, state, scans=1)
    assert loop.start_mode == "cold" and "checksum mismatch" in loop.start_reason
    assert newest.name in loop.start_reason
    loop.run()
    assert loop.runner.plc.scan_count == 1 and loop.runner.plc.marking() == {"p": 1}


def test_another_program_starts_cold_and_says_why(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    state = tmp_path / "state"
    make_loop(program, state, scans=30).run()
    changed = timed_program(tmp_path, TIMED.replace("delay: 500ms", "delay: 600ms"))
    old_hash = retain.from_bytes(next(state.glob("retain-*.json")).read_bytes())["program_hash"]
    loop = make_loop(changed, state, scans=1)
    assert loop.start_mode == "cold" and "differs from program timed" in loop.start_reason
    assert old_hash[:12] in loop.start_reason
    assert compile_file(changed).program_hash[:12] in loop.start_reason
    loop.run()
    assert loop.runner.plc.scan_count == 1 and loop.runner.plc.state is PlcState.RUNNING
    assert loop.runner.plc.marking() == {"p": 1}  # initial marking: nothing carried over


def test_no_snapshot_and_no_state_dir_are_cold(tmp_path: Path) -> None:
    loop = make_loop(timed_program(tmp_path), tmp_path / "state", scans=1)
    assert (loop.start_mode, loop.start_reason) == ("cold", f"no snapshot in {tmp_path / 'state'}")
    doc = loop.document()
    assert doc["start_mode"] == "cold" and doc["start_reason"].startswith("no snapshot")
    loop.run()
    plain = ScanLoop(LoopConfig(program=timed_program(tmp_path), max_scans=1), None, None,
                     VirtualClock())
    assert plain.start_mode == "cold" and plain.retain is None
    assert "retain off" in plain.document()["start_reason"]


# -- warm restart -----------------------------------------------------------------------------

def test_same_program_is_warm_with_marking_memory_and_timers_restored(tmp_path: Path) -> None:
    """Snapshot at scan time 200 ms: `work` (400 ms) is half done, `wait` (delay 500 ms) has
    200 ms behind it. The restart comes a long time later on the host's clock; the scan clock
    continues at 200 ms, so `work` completes at 400 ms and `wait` fires at 500 ms."""
    program = timed_program(tmp_path)
    state = tmp_path / "state"
    first = make_loop(program, state, scans=21)
    first.run()
    assert first.runner.plc.marking() == {"p": 1} and first.runner.plc.image.mw[0] == 0
    # %M as an HMI write leaves it; written between scans, retained on stop
    loop = make_loop(program, state, scans=21 + 1)
    loop.runner.plc.image.mw[0] = 4321
    loop.runner.plc.image.mx[5] = True
    loop.run()
    trace = tmp_path / "warm.trace.jsonl"
    warm = make_loop(program, state, scans=22 + 40, clock_ns=10**15, trace=trace)
    assert warm.start_mode == "warm", warm.start_reason
    assert "from scan 22" in warm.start_reason and warm.start_reason.endswith("RUNNING")
    plc = warm.runner.plc
    assert plc.state is PlcState.RUNNING and plc.scan_count == 22
    assert plc.marking() == {"p": 1}
    assert (int(plc.image.mw[0]), bool(plc.image.mx[5])) == (4321, True)
    assert plc.engine is not None and list(plc.engine.state.busy) == [1]  # `work` in progress
    warm.run()
    assert plc.marking() == {"x": 1, "e": 1}
    times = trace_times(trace)
    assert times == {"work done": 400 * MS, "wait": 500 * MS}
    assert warm.document()["retain"]["writes"] >= 1


def test_warm_start_stop_restores_and_waits_for_resume(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    state = tmp_path / "state"
    make_loop(program, state, scans=21).run()
    waiting = make_loop(program, state, scans=30, warm_start="stop", clock_ns=10**12)
    plc = waiting.runner.plc
    assert waiting.start_mode == "warm" and waiting.start_reason.endswith("STOPPED")
    assert plc.state is PlcState.STOPPED and plc.marking() == {"p": 1}
    waiting.scan_once(waiting.clock.now_ns())
    assert plc.image.get(plc.net.io.symbols["r"].address) == 0  # type: ignore[union-attr]
    waiting.pending.append(ProgramCommand(Command.RESUME))
    waiting.run()
    assert plc.state is PlcState.RUNNING and plc.marking() == {"p": 1}  # not the initial one
    assert plc.engine is not None and list(plc.engine.state.busy) == [1]
    # without --start a warm restart also waits STOPPED
    quiet = make_loop(program, state, scans=31, start=False)
    assert quiet.start_mode == "warm" and quiet.runner.plc.state is PlcState.STOPPED
    quiet.retain.close()  # type: ignore[union-attr]


class WriterPacedClock(VirtualClock):
    """A virtual clock whose scans wait (bounded) for the retain writer to take what was
    handed to it: on a virtual clock 100 scans take a few ms, and a loaded machine may not
    run the writer thread before the stop snapshot replaces the periodic ones (the writer
    keeps only the newest capture: a test then saw one write instead of several)."""

    def __init__(self) -> None:
        super().__init__(0)
        self.loop: ScanLoop | None = None

    def wait_until(self, deadline_ns: int) -> int:
        writer = self.loop.retain if self.loop is not None else None
        if writer is not None:
            give_up = time.monotonic() + 5
            while writer._pending is not None and time.monotonic() < give_up:
                time.sleep(0.001)
        return super().wait_until(deadline_ns)


def test_snapshots_at_the_interval_and_on_stop_keep_two_files(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    state = tmp_path / "state"
    clock = WriterPacedClock()
    config = LoopConfig(program=program, start=True, period_ns=10 * MS, max_scans=100,
                        state_dir=str(state), retain_interval_ns=100 * MS)  # 1 s of scan time
    loop = clock.loop = ScanLoop(config, None, None, clock)
    loop.run()
    info = loop.document()["retain"]
    assert info["writes"] >= 2 and info["errors"] == 0  # at least one periodic, and on stop
    files = sorted(state.glob("retain-*.json"))
    assert len(files) == retain.KEEP
    newest = retain.from_bytes(files[-1].read_bytes())
    assert newest["scan_count"] == 100  # the stop snapshot is the last scan's
    assert newest["seq"] == info["writes"] and newest["state"] == "RUNNING"


def test_the_writer_keeps_the_newest_capture_when_behind(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    loop = make_loop(program, tmp_path / "other", scans=5)
    loop.run()
    store = RetainStore.open(tmp_path / "state")
    writer = retain.RetainWriter(store)
    caps = [retain.capture(loop.runner.plc, n * MS, {}) for n in range(50)]
    for cap in caps:
        assert cap is not None
        writer.submit(cap)
    writer.close()
    newest = retain.from_bytes(store.files()[0].read_bytes())
    assert newest["now_ns"] == 49 * MS  # the last one always reaches the disk
    assert 1 <= writer.writes <= 50


# -- the state directory ----------------------------------------------------------------------

def test_a_second_runtime_on_one_state_dir_is_refused(tmp_path: Path) -> None:
    program = timed_program(tmp_path)
    state = tmp_path / "state"
    first = make_loop(program, state, scans=1)
    with pytest.raises(StateDirBusy, match=f"in use by another softplc \\(pid {os.getpid()}\\)"):
        make_loop(program, state, scans=1)
    first.run()  # stop releases the lock
    make_loop(program, state, scans=1).run()


def _hold_lock_forever(directory: str, locked: object) -> None:
    RetainStore.open(directory)
    locked.set()  # type: ignore[attr-defined]
    signal.pause()


def test_leftovers_of_a_killed_runtime_never_block(tmp_path: Path) -> None:
    state = tmp_path / "state"
    ctx = mp.get_context("fork")
    locked = ctx.Event()
    holder = ctx.Process(target=_hold_lock_forever, args=(str(state), locked))
    holder.start()
    try:
        assert locked.wait(30)
        with pytest.raises(StateDirBusy, match=f"pid {holder.pid}"):
            RetainStore.open(state)
    finally:
        os.kill(holder.pid, signal.SIGKILL)  # type: ignore[arg-type]
        holder.join(10)
    assert (state / retain.LOCK_FILE).exists()  # the lock file stays behind, harmless
    (state / ".retain-000000007.json.999.tmp").write_bytes(b'{"format": 1, "len')
    store = RetainStore.open(state)
    assert not list(state.glob(".*.tmp"))  # a half-written snapshot is removed, never loaded
    assert store.load_newest() == (None, [])
    store.close()


def test_the_field_state_loader_refuses_anything_but_plant_models() -> None:
    import base64
    import pickle

    from softplc.devices.plants.transport import TransportPlant

    plant = TransportPlant(seed=3)
    plant.set_actuators({"m1": 1, "m2": 0})
    plant.advance(3_000_000_000)
    again = retain.load_plant(base64.b64encode(pickle.dumps(plant)).decode())
    assert isinstance(again, TransportPlant) and again.report() == plant.report()
    evil = base64.b64encode(pickle.dumps(os.system)).decode()
    with pytest.raises(pickle.UnpicklingError, match="not a plant model"):
        retain.load_plant(evil)


# -- `softplc run` ----------------------------------------------------------------------------

def softplc_run(state: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--modbus", "off", "--opcua", "off", "--api", "off", "--state-dir", str(state), "--quiet",
         "--period", "5ms", "--retain-interval", "100ms", *extra],
        cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_softplc_run_restarts_warm_and_says_so(tmp_path: Path) -> None:
    state = tmp_path / "state"
    first = softplc_run(state, "--duration", "1s")
    assert first.returncode == 0, first.stderr
    assert f"cold start: no snapshot in {state}" in first.stdout
    # the boot policy warm (docs/retain.md): a restart resumes what was RUNNING
    second = softplc_run(state, "--duration", "500ms", "--boot-policy", "warm")
    assert second.returncode == 0, second.stderr
    assert "warm start: snapshot retain-" in second.stdout and "-> RUNNING" in second.stdout
    scans = [int(part.split("=")[1]) for line in (first.stdout, second.stdout)
             for part in line.split() if part.startswith("scans=")]
    assert scans[1] > scans[0]  # the scan count went on from the snapshot


def test_softplc_run_refuses_a_state_dir_in_use(tmp_path: Path) -> None:
    store = RetainStore.open(tmp_path / "state")
    try:
        busy = softplc_run(tmp_path / "state", "--duration", "1s")
    finally:
        store.close()
    assert busy.returncode == 1
    assert "is in use by another softplc" in busy.stderr and str(os.getpid()) in busy.stderr
