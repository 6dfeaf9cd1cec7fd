"""The shared-memory snapshot: round trip, layout checks, stale segments, and consistency
across real processes."""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from multiprocessing.shared_memory import SharedMemory
from multiprocessing.synchronize import Event
from pathlib import Path

import numpy as np
import pytest

from softplc.core.image import ImageSizes, ProcessImage
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import Snapshot, Status
from softplc.runtime.shared.shm import SnapshotLayoutError, SnapshotReader, SnapshotWriter

SPAWN = mp.get_context("spawn")


@pytest.fixture
def writer() -> Iterator[SnapshotWriter]:
    with SnapshotWriter.create() as w:
        yield w


def _random_image(sizes: ImageSizes, seed: int) -> ProcessImage:
    rng = np.random.default_rng(seed)
    image = ProcessImage(sizes)
    for name in ("ix", "qx", "mx"):
        getattr(image, name)[:] = rng.integers(0, 2, sizes.bits).astype(bool)
    for name in ("iw", "qw", "mw"):
        getattr(image, name)[:] = rng.integers(0, 0x10000, sizes.words)
    return image


def test_round_trip_of_every_area_and_status_field(writer: SnapshotWriter) -> None:
    status = Status(
        state=PlcState.FAULTED,
        scan_count=2**40 + 3,
        last_exec_us=123,
        max_exec_us=4567,
        p99_lateness_us=89,
        overruns=7,
        program_hash="0123456789abcdef" * 4,
        fault_code=1,
        period_us=10_000,
    )
    image = _random_image(writer.sizes, seed=1)
    with SnapshotReader.attach(writer.name, writer.sizes) as reader:
        assert writer.publish(image, status) == 1
        snap = reader.latest()
        assert snap.seq == 1 and reader.seq == 1
        assert snap.status == status
        for name in ("ix", "qx", "mx", "iw", "qw", "mw"):
            got, want = getattr(snap.image, name), getattr(image, name)
            assert got.dtype == want.dtype and got.shape == want.shape
            assert np.array_equal(got, want), name
        assert snap.image.sizes == writer.sizes
        assert writer.publish(_random_image(writer.sizes, 2), Status()) == 2
        assert reader.latest().status == Status()


def test_before_the_first_publish_the_snapshot_is_empty(writer: SnapshotWriter) -> None:
    with SnapshotReader.attach(writer.name, writer.sizes) as reader:
        snap = reader.latest()
    assert snap.seq == 0 and snap.status == Status()
    assert snap.image.equals(ProcessImage(writer.sizes))


def test_a_snapshot_is_a_private_copy(writer: SnapshotWriter) -> None:
    image = ProcessImage(writer.sizes)
    image.mw[3] = 42
    writer.publish(image, Status())
    with SnapshotReader.attach(writer.name, writer.sizes) as reader:
        first = reader.latest()
        first.image.mw[3] = 7
        first.image.qx[0] = True
        image.mw[3] = 43  # changing the source after publish does not reach readers either
        second = reader.latest()
    assert second.image.mw[3] == 42 and not second.image.qx[0]


def test_publish_rejects_wrong_sizes_and_long_hash(writer: SnapshotWriter) -> None:
    with pytest.raises(ValueError, match="sizes"):
        writer.publish(ProcessImage(ImageSizes(bits=16, words=4)), Status())
    with pytest.raises(ValueError, match="at most 64"):
        writer.publish(ProcessImage(writer.sizes), Status(program_hash="a" * 65))
    assert writer.seq == 0


def test_attach_with_wrong_sizes_is_a_clear_error() -> None:
    with SnapshotWriter.create(ImageSizes(bits=16, words=8)) as w:
        with pytest.raises(SnapshotLayoutError, match="16 bits and 8 words") as err:
            SnapshotReader.attach(w.name, ImageSizes())
        assert "expects 800 bits and 1024 words" in str(err.value)


def test_attach_to_something_else_is_a_clear_error() -> None:
    other = SharedMemory(create=True, size=4096)
    try:
        with pytest.raises(SnapshotLayoutError, match=r"not .*a softplc snapshot"):
            SnapshotReader.attach(other.name, ImageSizes())
    finally:
        other.close()
        other.unlink()


def test_attach_to_a_missing_segment_names_it() -> None:
    with pytest.raises(FileNotFoundError, match="softplc-missing-x"):
        SnapshotReader.attach("softplc-missing-x", ImageSizes())


def test_reader_is_picklable_and_refuses_reads_once_closed(writer: SnapshotWriter) -> None:
    writer.publish(_random_image(writer.sizes, 3), Status(scan_count=9))
    with SnapshotReader.attach(writer.name, writer.sizes, max_attempts=50) as reader:
        clone = pickle.loads(pickle.dumps(reader))
    with pytest.raises(ValueError, match="closed"):
        reader.latest()
    with clone:
        assert clone.latest().status.scan_count == 9 and clone.max_attempts == 50


def _die_holding(name: str, ready: Event) -> None:
    with SnapshotWriter.create(ImageSizes(), name) as w:
        w.publish(ProcessImage(), Status(scan_count=99))
        ready.set()
        ready.wait()  # set already: fall through to the parent's kill() without cleanup
        os.kill(os.getpid(), 9)


def test_a_killed_run_does_not_block_a_restart() -> None:
    name = f"softplc-test-stale-{os.getpid()}"
    ready = SPAWN.Event()
    child = SPAWN.Process(target=_die_holding, args=(name, ready))
    child.start()
    child.join(timeout=60)
    assert child.exitcode == -9 and ready.is_set()
    with SnapshotReader.attach(name, ImageSizes()) as leftover:  # nobody unlinked it
        assert leftover.latest().status.scan_count == 99
    with SnapshotWriter.create(ImageSizes(), name) as w, SnapshotReader.attach(name, w.sizes) as r:
        assert r.latest().seq == 0 and r.latest().status.scan_count == 0  # fresh, not reused
        w.publish(ProcessImage(), Status(scan_count=1))
        assert r.latest().status.scan_count == 1


def test_a_stale_segment_of_another_size_is_replaced() -> None:
    name = f"softplc-test-stale2-{os.getpid()}"
    stale = SharedMemory(name=name, create=True, size=100)
    stale.close()  # left behind; its unlink is now the new writer's job
    sizes = ImageSizes(bits=32, words=16)
    with SnapshotWriter.create(sizes, name) as w, SnapshotReader.attach(name, sizes) as r:
        assert r.latest().image.sizes == sizes and w.name == name


def _publish_seq_images(name: str, sizes: ImageSizes, ready: Event, stop: Event) -> None:
    image = ProcessImage(sizes)
    with SnapshotWriter.create(sizes, name) as writer:
        ready.set()
        for seq in range(1, 10_000_000):
            bit, word = bool(seq & 1), seq & 0xFFFF
            for area in (image.ix, image.qx, image.mx):
                area.fill(bit)
            for area in (image.iw, image.qw, image.mw):
                area.fill(word)
            status = Status(
                scan_count=seq,
                last_exec_us=seq,
                max_exec_us=seq,
                p99_lateness_us=seq,
                overruns=seq,
                program_hash=f"{seq:064x}",
                fault_code=seq,
                period_us=seq,
            )
            assert writer.publish(image, status) == seq
            if stop.is_set():
                break


def _assert_whole(snap: Snapshot) -> None:
    seq = snap.seq
    assert snap.status.scan_count == seq
    if seq == 0:
        return
    s = snap.status
    assert s.last_exec_us == s.max_exec_us == s.p99_lateness_us == s.overruns == seq
    assert s.fault_code == s.period_us == seq and s.program_hash == f"{seq:064x}"
    for area in (snap.image.ix, snap.image.qx, snap.image.mx):
        assert np.all(area == bool(seq & 1)), f"bits of publish {seq} mixed"
    for area in (snap.image.iw, snap.image.qw, snap.image.mw):
        assert np.all(area == seq & 0xFFFF), f"words of publish {seq} mixed"


def test_snapshots_are_never_mixed_across_processes() -> None:
    sizes = ImageSizes()
    name = f"softplc-test-seq-{os.getpid()}"
    ready, stop = SPAWN.Event(), SPAWN.Event()
    child = SPAWN.Process(target=_publish_seq_images, args=(name, sizes, ready, stop))
    child.start()
    try:
        assert ready.wait(timeout=60), "writer process did not start"
        with SnapshotReader.attach(name, sizes) as reader:
            seen: set[int] = set()
            last = 0
            # Bounded: at least 5 000 snapshots checked, at most 100 000 (a few seconds).
            for reads in range(1, 100_001):
                snap = reader.latest()
                _assert_whole(snap)
                assert snap.seq >= last, "sequence went backwards"
                last = snap.seq
                seen.add(snap.seq)
                if reads >= 5_000 and len(seen) >= 500:
                    break
    finally:
        stop.set()
        child.join(timeout=30)
    assert child.exitcode == 0
    assert len(seen) >= 20, "the writer was not publishing while the reader read"


_CLEAN_EXIT = textwrap.dedent(
    """
    import multiprocessing as mp
    import subprocess
    import sys
    from softplc.core.image import ImageSizes, ProcessImage
    from softplc.core.snapshot import Status
    from softplc.runtime.shared.shm import SnapshotReader, SnapshotWriter

    def read(name):
        with SnapshotReader.attach(name, ImageSizes()) as reader:
            assert reader.latest().status.scan_count == 5

    if __name__ == "__main__":
        for method in ("spawn", "fork"):
            with SnapshotWriter.create() as writer:
                writer.publish(ProcessImage(), Status(scan_count=5))
                child = mp.get_context(method).Process(target=read, args=(writer.name,))
                child.start()
                child.join()
                assert child.exitcode == 0
                # A reader in an unrelated interpreter has its own resource tracker, which
                # would unlink the segment at its exit if the reader had registered it.
                code = f"import clean_exit; clean_exit.read({writer.name!r})"
                subprocess.run([sys.executable, "-c", code], check=True, cwd=sys.path[0])
                read(writer.name)
        try:
            SnapshotReader.attach(writer.name, ImageSizes())
        except FileNotFoundError:
            print("unlinked")
    """
)


def test_normal_exit_leaves_no_segment_and_no_tracker_warning(tmp_path: Path) -> None:
    script = tmp_path / "clean_exit.py"
    script.write_text(_CLEAN_EXIT)
    result = subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "unlinked"
    assert result.stderr == ""
