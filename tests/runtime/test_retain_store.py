"""Retain that cannot lie (issue 19 part 2), through a fault-injecting file layer: short
writes are continued, ENOSPC / EIO / a failed rename / a file that reads back different are
counted by stage, never renamed into place, the temporary removed and the older valid
snapshots kept; a damaged older file does not count as one of the two kept; the writer thread
survives a value that is not JSON and a bug in the layer, and `stop` writes the final
snapshot synchronously and says whether it did. The real-disk counterpart (a full tmpfs, a
kill -9) is tests/runtime/test_retain_tmpfs.py.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any

import pytest

from softplc.core.lifecycle import Command
from softplc.core.plc import ProgramCommand
from softplc.runtime.retain import writer as retain
from softplc.runtime.retain.writer import FileOps, RetainStore, RetainWriter, Stage, WriteFailed
from tests.core.helpers import Bench, compile_program
from tests.support import eventually


def payload(seq: int, size: int = 200) -> dict[str, Any]:
    return {"seq": seq, "program_hash": "h" * 64, "fill": "x" * size}


def snapshot_seqs(store: RetainStore) -> list[int]:
    return [retain.from_bytes(p.read_bytes())["seq"] for p in store.files()]


def temporaries(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


class Faulty(FileOps):
    """A disk with `free` bytes left (ENOSPC beyond, after a short write), writes of at most
    `chunk` bytes, and optional failures of fsync, rename, unlink, or a flipped byte."""

    def __init__(self) -> None:
        self.free: int | None = None
        self.chunk: int | None = None
        self.zero_write = False
        self.fail: dict[str, OSError | Exception] = {}
        self.flip = False

    def _maybe(self, name: str) -> None:
        if name in self.fail:
            raise self.fail[name]

    def write(self, fd: int, data: memoryview) -> int:
        if self.zero_write:
            return 0
        n = len(data) if self.chunk is None else min(self.chunk, len(data))
        if self.free is not None:
            if self.free == 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            n = min(n, self.free)
            self.free -= n
        part = bytes(data[:n])
        if self.flip and n > 40:
            part = part[:-1] + bytes([part[-1] ^ 1])  # what a bad sector or driver would do
        return os.write(fd, part)

    def fsync(self, fd: int) -> None:
        self._maybe("fsync")
        super().fsync(fd)

    def replace(self, src: Path, dst: Path) -> None:
        self._maybe("replace")
        super().replace(src, dst)

    def unlink(self, path: Path) -> None:
        self._maybe("unlink")
        super().unlink(path)


@pytest.fixture
def faulty(tmp_path: Path) -> tuple[RetainStore, Faulty]:
    ops = Faulty()
    store = RetainStore.open(tmp_path / "state", ops=ops)
    for seq in (1, 2, 3):
        store.write(payload(seq))
    yield store, ops
    store.close()


def test_short_writes_are_continued_into_a_complete_snapshot(
        faulty: tuple[RetainStore, Faulty]) -> None:
    store, ops = faulty
    ops.chunk = 7
    path = store.write(payload(4, size=5000))
    assert retain.from_bytes(path.read_bytes())["fill"] == "x" * 5000
    assert snapshot_seqs(store) == [4, 3]


@pytest.mark.parametrize(("fault", "stage", "text"), [
    ("enospc", Stage.WRITE, "ENOSPC"),
    ("zero", Stage.WRITE, "short write"),
    ("fsync", Stage.FSYNC, "EIO"),
    ("replace", Stage.RENAME, "EXDEV"),
    ("flip", Stage.VERIFY, "read back is not what was written"),
])
def test_a_failed_write_keeps_the_older_snapshots_and_leaves_no_temporary(
        faulty: tuple[RetainStore, Faulty], fault: str, stage: Stage, text: str) -> None:
    store, ops = faulty
    if fault == "enospc":
        ops.free = 1000  # part of the file fits: a short write, then ENOSPC
    elif fault == "zero":
        ops.zero_write = True
    elif fault == "fsync":
        ops.fail["fsync"] = OSError(errno.EIO, "Input/output error")
    elif fault == "replace":
        ops.fail["replace"] = OSError(errno.EXDEV, "Invalid cross-device link")
    else:
        ops.flip = True
    with pytest.raises(WriteFailed) as err:
        store.write(payload(4, size=5000))
    assert err.value.stage is stage and text in str(err.value)
    assert snapshot_seqs(store) == [3, 2]  # nothing older deleted, nothing bad renamed
    assert temporaries(store.directory) == []
    loaded, skipped = store.load_newest()
    assert loaded is not None and loaded.payload["seq"] == 3 and skipped == []


def test_a_temporary_that_cannot_be_removed_is_counted_and_removed_at_the_next_open(
        faulty: tuple[RetainStore, Faulty], tmp_path: Path) -> None:
    store, ops = faulty
    ops.free = 100
    ops.fail["unlink"] = OSError(errno.EROFS, "Read-only file system")
    with pytest.raises(WriteFailed):
        store.write(payload(4, size=5000))
    assert store.cleanup_errors >= 1 and len(temporaries(store.directory)) == 1
    store.close()
    again = RetainStore.open(store.directory)
    assert temporaries(store.directory) == [] and again.temps_removed == 1
    again.close()


def test_an_older_snapshot_damaged_on_disk_is_not_one_of_the_two_kept(
        faulty: tuple[RetainStore, Faulty]) -> None:
    store, _ = faulty
    newest = store.files()[0]
    data = bytearray(newest.read_bytes())
    data[-5] ^= 1
    newest.write_bytes(bytes(data))  # seq 3 rots after it was written
    store.write(payload(4))
    assert snapshot_seqs(store) == [4, 2]  # the damaged 3 is gone, 2 is kept as the second


def test_the_newest_file_is_never_deleted_before_a_newer_one_is_verified(
        faulty: tuple[RetainStore, Faulty]) -> None:
    store, ops = faulty
    ops.free = 0
    for seq in range(4, 10):  # a disk that stays full: every write fails
        with pytest.raises(WriteFailed):
            store.write(payload(seq))
    assert snapshot_seqs(store) == [3, 2] and temporaries(store.directory) == []
    ops.free = None
    store.write(payload(store.seq + 1))  # the disk has room again: the sequence goes on
    assert snapshot_seqs(store) == [4, 3]


# -- the writer thread ------------------------------------------------------------------------

COLOURED = """
places:
  parts: {tokens: [{id: 1, tag: 'a'}]}
  done: {coloured: true}
transitions:
  move: {from: [{place: parts, var: p}], to: [{place: done, token: p}]}
"""


def a_capture(tmp_path: Path, bad: object = None) -> retain.Capture:
    bench = Bench(compile_program(tmp_path, COLOURED), start=False)
    bench.scan(0, [ProgramCommand(Command.START)])
    if bad is not None:
        assert bench.plc.engine is not None
        bench.plc.engine.state.tokens[1] = [{"when": bad}]
    cap = retain.capture(bench.plc, 1_000_000, {})
    assert cap is not None
    return cap


def test_the_writer_survives_a_bad_value_and_a_bug_and_counts_both(tmp_path: Path) -> None:
    import datetime

    ops = Faulty()
    writer = RetainWriter(RetainStore.open(tmp_path / "state", ops=ops))
    bad = writer._write(a_capture(tmp_path, datetime.date(2024, 1, 1)))  # what submit runs
    assert not bad.written and "field 'when'" in bad.error and "the date 2024-01-01" in bad.error
    ops.fail["fsync"] = RuntimeError("a bug in a layer")
    writer.submit(a_capture(tmp_path))
    final = writer.close()
    info = writer.info()
    assert not final.written and "RuntimeError: a bug in a layer" in final.error
    assert info["errors"] == 2 and info["errors_by_stage"]["encode"] == 1
    assert info["errors_by_stage"]["other"] == 1 and info["writes"] == 0
    assert info["final"] == {"written": False, "path": "", "error": final.error}
    ops.fail.clear()
    writer = RetainWriter(RetainStore.open(tmp_path / "state", ops=ops))
    writer.submit(a_capture(tmp_path, 1.5))  # the thread counts it and goes on
    writer.submit(a_capture(tmp_path))
    result = writer.stop(a_capture(tmp_path))
    assert result.written and writer.info()["writes"] >= 1 and writer._thread.is_alive() is False
    assert str(result) == f"final snapshot {result.path} written"


def test_stop_writes_the_final_snapshot_synchronously_and_says_so(tmp_path: Path) -> None:
    ops = Faulty()
    writer = RetainWriter(RetainStore.open(tmp_path / "state", ops=ops))
    cap = a_capture(tmp_path)
    result = writer.stop(cap)
    files = sorted((tmp_path / "state").glob("retain-*.json"))
    assert result.written and [f.name for f in files] == [result.path]
    assert retain.from_bytes(files[0].read_bytes())["scan_count"] == cap.scan_count

    ops.free = 0
    writer = RetainWriter(RetainStore.open(tmp_path / "state", ops=ops))
    result = writer.stop(a_capture(tmp_path))
    assert not result.written and result.error.startswith("write: ")
    assert "ENOSPC" in result.error and str(result).startswith("final snapshot NOT written")
    assert writer.info()["errors_by_stage"]["write"] == 1
    assert temporaries(tmp_path / "state") == []


# -- issue 43: what the codec carries, and the two files kept, checked on their own ------------

ROUND_TRIP = """
places:
  parts: {tokens: [{id: 1, kg: 2.5, tag: 'a', ok: true}, {id: 2, kg: 7.25, tag: 'b', ok: false},
                   {id: 3, kg: 0.5, tag: 'c', ok: true}]}
  done: {coloured: true}
  count: {tokens: 3}
transitions:
  move:
    from: [count, {place: parts, var: p}]
    to: [{place: done, token: {id: "p.id", kg: "p.kg * 2", tag: "p.tag", ok: "p.ok"}}]
"""


def _restored(tmp_path: Path, bench: Bench, resume: bool) -> Bench:
    """`bench`'s PLC captured, encoded to JSON text and back, restored into a fresh PLC."""
    import json
    cap = retain.capture(bench.plc, 5_000_000, {})
    assert cap is not None
    payload = json.loads(json.dumps(retain.encode(cap, 1, 0)))
    again = Bench(bench.net, start=False)
    retain.restore(again.plc, payload, resume)
    return again


def test_coloured_tokens_survive_a_retain_round_trip(tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, ROUND_TRIP), start=False)
    bench.scan(0, [ProgramCommand(Command.START)])
    assert bench.plc.engine is not None
    tokens = bench.plc.engine.state.tokens
    parts, done = bench.net.place_index["parts"], bench.net.place_index["done"]
    assert len(tokens[parts]) == 2 and len(tokens[done]) == 1  # one moved in the first scan
    again = _restored(tmp_path, bench, resume=True)
    assert again.plc.engine is not None
    assert again.plc.engine.state.tokens == tokens
    assert again.plc.engine.state.tokens[done][0] == {"id": 1, "kg": 5.0, "tag": "a", "ok": True}
    assert again.marking() == bench.marking()


def test_a_faulted_plc_is_restored_faulted_with_its_reason(tmp_path: Path) -> None:
    from softplc.core.lifecycle import PlcState
    from softplc.core.problems import FaultCode
    bench = Bench(compile_program(tmp_path, ROUND_TRIP))
    bench.plc.fault(FaultCode.DEVICE, 1_000_000, reason="device press: no answer for 3 s")
    again = _restored(tmp_path, bench, resume=False)
    assert again.plc.state is PlcState.FAULTED
    assert (again.plc.fault_code, again.plc.fault_reason) == (
        FaultCode.DEVICE, "device press: no answer for 3 s")


def test_the_store_keeps_the_two_newest_snapshots(tmp_path: Path) -> None:
    store = RetainStore.open(tmp_path / "state")  # the default keep: KEEP, 2
    try:
        for seq in (1, 2):
            store.write(payload(seq))
        assert snapshot_seqs(store) == [2, 1]
        store.write(payload(3))
        assert snapshot_seqs(store) == [3, 2]  # a third write deletes the oldest
    finally:
        store.close()


PAUSED = """
places:
  idle: {tokens: 1}
  busy: {}
  early: {tokens: 1}
  late: {}
transitions:
  go:   {from: [idle], to: [busy]}
  tick: {from: [early], to: [late], delay: 20ms}
  back: {from: [busy], to: [idle], delay: 50ms}
"""


def test_a_capture_while_paused_moves_the_timers_past_the_pause(tmp_path: Path) -> None:
    """A snapshot taken at a breakpoint holds the net as it will run on: `back`'s delay,
    started at 10 ms, moves by the 30 ms paused (the pause at 20 ms, the last scan at 50)."""
    ms = 1_000_000
    bench = Bench(compile_program(tmp_path, PAUSED))
    bench.scan(10 * ms, [ProgramCommand(Command.BREAK, symbol="fire:tick", value=1)])
    for now in (20, 30, 40, 50):
        bench.scan(now * ms)
    assert bench.plc.debug.pause is not None and bench.plc.engine is not None
    back = bench.net.transitions[2].index
    assert bench.plc.engine.state.enabled_since == {back: 10 * ms}
    cap = retain.capture(bench.plc, 50 * ms, {})
    assert cap is not None and cap.net_state.enabled_since == {back: 40 * ms}
    assert bench.plc.engine.state.enabled_since == {back: 10 * ms}  # the PLC's own: unchanged


def test_restore_starts_a_retain_none_memory_symbol_anew(tmp_path: Path) -> None:
    """restore()'s own contract (docs/retain.md): a `retain: none` memory symbol restarts at
    its `init:` whatever the snapshot holds; a retained one takes the snapshot's value."""
    (tmp_path / "io.yaml").write_text("""sizes: {bits: 16, words: 16}
symbols:
  scratch_w: {address: '%MW0', retain: none, init: 5}
  setpoint: {address: '%MW1'}
""")
    bench = Bench(compile_program(tmp_path, "places:\n  p: {tokens: 1}\n"))
    bench.plc.image.mw[:2] = (11, 22)  # as HMI writes would leave them
    again = _restored(tmp_path, bench, resume=True)
    assert (int(again.plc.image.mw[0]), int(again.plc.image.mw[1])) == (5, 22)


def test_restore_starts_a_retain_none_coloured_place_with_its_initial_records(
        tmp_path: Path) -> None:
    bench = Bench(compile_program(tmp_path, """
places:
  src: {tokens: [{n: 1}, {n: 2}]}
  seen: {retain: none, tokens: [{n: 0}]}
transitions:
  look: {from: [{place: src, var: v}], to: [{place: seen, token: v}]}
"""))
    bench.scan(10)
    assert bench.plc.engine is not None
    seen = bench.net.place_index["seen"]
    assert len(bench.plc.engine.state.tokens[seen]) > 1  # look moved records into it
    again = _restored(tmp_path, bench, resume=True)
    assert again.plc.engine is not None
    assert again.plc.engine.state.tokens[seen] == [{"n": 0}]
    assert again.plc.engine.state.tokens[bench.net.place_index["src"]] == \
        bench.plc.engine.state.tokens[bench.net.place_index["src"]]


def test_a_cold_start_keeps_only_the_persistent_memory_the_snapshot_kept_the_same(
        tmp_path: Path) -> None:
    """restore_persistent: a persistent symbol is taken back only when the snapshot's program
    kept the same variable there (name, address, type, scale): `other` became an INT."""
    import json
    io = """sizes: {{bits: 16, words: 16}}
symbols:
  total_w: {{address: '%MW2', retain: persistent}}
  other: {{address: '%MW3', retain: persistent{kind}}}
"""
    benches = []
    for name, kind in (("v1", ""), ("v2", ", type: int")):
        (tmp_path / name).mkdir()
        (tmp_path / name / "io.yaml").write_text(io.format(kind=kind))
        benches.append(Bench(compile_program(tmp_path / name, "places:\n  p: {tokens: 1}\n"),
                            start=False))
    old, new = benches
    old.plc.image.mw[2:4] = (33, 44)
    cap = retain.capture(old.plc, 0, {})
    assert cap is not None
    payload = json.loads(json.dumps(retain.encode(cap, 1, 0)))
    assert retain.restore_persistent(new.plc, payload) == ["total_w"]
    assert (int(new.plc.image.mw[2]), int(new.plc.image.mw[3])) == (33, 0)


def test_a_cold_start_takes_back_a_persistent_coloured_place_with_its_records(
        tmp_path: Path) -> None:
    import json
    net = compile_program(tmp_path, """
places:
  src: {tokens: [{n: 1}]}
  kept: {retain: persistent, tokens: [{n: 0}]}
transitions:
  keep: {from: [{place: src, var: v}], to: [{place: kept, token: v}]}
""")
    old = Bench(net)
    old.scan(10)
    cap = retain.capture(old.plc, 10, {})
    assert cap is not None
    payload = json.loads(json.dumps(retain.encode(cap, 1, 0)))
    new = Bench(net, start=False)
    assert retain.restore_persistent(new.plc, payload) == ["kept"]
    assert new.plc.engine is not None
    assert new.plc.engine.state.tokens[net.place_index["kept"]] == [{"n": 0}, {"n": 1}]
    assert new.marking() == {"src": 1, "kept": 2}  # src is not persistent: initial


def test_a_held_capture_waits_for_settle_and_close_writes_it(tmp_path: Path) -> None:
    """submit(later=True) (the paced scan loop) wakes nothing until settle(); close() writes
    a capture still held, as it writes one still pending."""
    writer = RetainWriter(RetainStore.open(tmp_path / "state", ops=Faulty()))
    writer.submit(a_capture(tmp_path), later=True)
    assert writer.writes == 0 and writer._pending is None  # the thread was not woken
    writer.settle()
    eventually(lambda: writer.writes == 1, 10, "the settled capture written")
    writer.submit(a_capture(tmp_path), later=True)  # held again: close() must not lose it
    final = writer.close()
    assert final.written and writer.writes == 2, (final, writer.writes)
