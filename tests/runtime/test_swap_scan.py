"""The swap scan of an online change only swaps, fires and publishes (issue 40 item 8): what
its board shows of the new program is described while the download is prepared, between
scans (runtime/netview.py, `prewarm`); the board itself goes out after the scan, then the
snapshot with the new program's hash, then the reply (runtime/publisher.py, runtime/loop.py
`_slack`).

Before, the swap scan described the new program for its board (its structure and symbols,
~0.1-0.4 ms) and sent the reply (~0.1 ms) before publishing that board: at a 1 ms period
every change missed the slot after its swap scan, and a client told "applied" could read
the board of the program before."""

from __future__ import annotations

import sys
import threading
import uuid
from pathlib import Path
from typing import Any

import pytest

from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.snapshot import CommandReply, CommandRequest, Status
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime import netview
from softplc.runtime.config import LoopConfig
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.shm import SnapshotWriter
from tests.runtime.test_dry_run_off_scan import WatchedLoop as InScan

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = ROOT / "programs" / "transport.yaml"
Record = list[tuple[str, Any]]


class WatchedLoop(InScan):
    """A loop that says whether its thread is in a scan (the program's scan and its publish:
    what the scan's execution time counts) right now."""

    def _publish(self, now_ns: int) -> None:
        self.in_scan = True
        try:
            super()._publish(now_ns)
        finally:
            self.in_scan = False


class RecordingBoard(StatusBoard):
    """The real board, noting the program of each document it publishes, and each one
    published inside a scan."""

    record: Record
    loop: WatchedLoop | None = None

    def publish(self, document: dict[str, Any]) -> None:
        super().publish(document)
        if hasattr(self, "record"):
            self.record.append(("board", document.get("program_hash")))
            if self.loop is not None and self.loop.in_scan:
                self.record.append(("board inside a scan", document.get("program_hash")))


class RecordingWriter(SnapshotWriter):
    """The real snapshot segment, noting each program hash it publishes first."""

    record: Record

    def publish(self, image: ProcessImage, status: Status) -> int:
        published = super().publish(image, status)
        if ("snapshot", status.program_hash) not in self.record:
            self.record.append(("snapshot", status.program_hash))
        return published


class RecordingChannel(Channel):
    """The real channel, noting each reply when it is sent (a held one: when sent)."""

    record: Record

    def reply(self, reply: CommandReply, later: bool = False) -> None:
        super().reply(reply, later)
        if not later:
            self.record.append(("reply", reply.id))


def _online_change(monkeypatch: pytest.MonkeyPatch,
                   state_dir: Path | None = None) -> tuple[Record, str, Record]:
    """One online change of the transport system on a paced loop: what was published and
    sent, in order; the new program's hash; each program drawn for a board, with whether
    that was inside a scan."""
    record: Record = []
    drawn: Record = []
    channel = RecordingChannel()
    channel.record = record
    board = RecordingBoard.create(f"softplc_test_{uuid.uuid4().hex[:12]}")
    assert isinstance(board, RecordingBoard)
    board.record = record
    config = LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                        period_ns=10_000_000,
                        state_dir=None if state_dir is None else str(state_dir))
    writer = RecordingWriter.create(config.sizes)
    assert isinstance(writer, RecordingWriter)
    writer.record = record
    loop = WatchedLoop(config, channel, writer, board=board)
    board.loop = loop
    text = TRANSPORT.read_text() + "\n# the same net, another text\n"
    draw = netview._drawn

    def watched(net: CompiledNet) -> dict[str, Any]:
        drawn.append((net.program_hash, loop.in_scan))
        return draw(net)
    monkeypatch.setattr(netview, "_drawn", watched)
    stop = threading.Event()
    thread = threading.Thread(target=loop.run, args=(stop,), daemon=True)
    try:
        thread.start()
        reply = channel.send_command(CommandRequest(
            7, Command.DOWNLOAD, program_text=text, program_path=str(TRANSPORT), online=True),
            timeout_s=60)
        assert reply.ok, reply.message
        new_hash = loop.runner.plc.net.program_hash if loop.runner.plc.net else ""
    finally:
        stop.set()
        thread.join(30)
        board.close()
        writer.close()
        writer.unlink()
        channel.close()
    assert not thread.is_alive()
    return record, new_hash, drawn


def test_the_new_programs_board_is_described_before_its_swap_scan(
        monkeypatch: pytest.MonkeyPatch) -> None:
    netview._cache.clear()  # the transport system described by another test: not here
    record, new_hash, drawn = _online_change(monkeypatch)
    assert ("board", new_hash) in record
    described = [in_scan for program, in_scan in drawn if program == new_hash]
    assert described, f"the new program was never described: {drawn}"
    assert not any(described), f"described inside a scan: {drawn}"


def test_a_reply_goes_after_the_board_that_shows_its_program(
        monkeypatch: pytest.MonkeyPatch) -> None:
    record, new_hash, _ = _online_change(monkeypatch)
    assert ("reply", 7) in record and ("board", new_hash) in record, record
    assert record.index(("board", new_hash)) < record.index(("reply", 7)), record


def test_the_board_goes_out_after_the_scan_then_the_new_hash_then_the_reply(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The board is a view, not the scan's I/O: its document and JSON (0.3-0.7 ms of a 1 ms
    scan in the scan process) are published in the slack after the scan, every refresh and
    the swap's; the snapshot of the swap scan follows its board there (a service that sees
    the new hash finds the program's symbols), and the reply follows both. On 5a232ec every
    board was published inside the scan."""
    record, new_hash, _ = _online_change(monkeypatch)
    inside = [entry for entry in record if entry[0] == "board inside a scan"]
    assert not inside, f"boards published inside a scan: {inside}"
    assert sum(1 for kind, _ in record if kind == "board") >= 2, record
    order = [record.index(entry) for entry in
             (("board", new_hash), ("snapshot", new_hash), ("reply", 7))]
    assert order == sorted(order), record


def test_a_net_is_described_once_what_its_hash_leaves_out_too_and_no_net_is_kept(
        tmp_path: Path) -> None:
    """netview's cache: a compiled net described once, the running program's and the next
    one's (KEPT); two compiles of programs whose hash is the same but whose io images differ
    in what the hash leaves out (a description, a unit) each shown as they are (keyed by the
    hash alone, the second showed the first's: CI caught it in
    tests/hmi/test_nonfinite_modbus.py, when the hash still left `finite:` out); a net
    itself never kept there."""
    netview._cache.clear()
    tank = ROOT / "programs" / "tank.yaml"
    first = compile_file(str(tank))
    described = netview.described(first)
    assert netview.described(first) is described
    assert described.structure["program_hash"] == first.program_hash
    assert [s.name for s, _ in described.symbols] == list(first.io.symbols)
    # The same program, its setpoint described otherwise: the same hash (the hash leaves a
    # text out), not the same board (what the doors show is what the board says).
    (tmp_path / "programs").mkdir()
    (tmp_path / "io_images").mkdir()
    (tmp_path / "programs" / "tank.yaml").write_text(tank.read_text())
    io = (ROOT / "io_images" / "tank.yaml").read_text()
    cut = io.index('description: "', io.index("fill_to:")) + len('description: "')
    io = io[:cut] + "RENAMED " + io[cut:]
    (tmp_path / "io_images" / "tank.yaml").write_text(io)
    changed = compile_file(str(tmp_path / "programs" / "tank.yaml"))
    assert changed.program_hash == first.program_hash
    fixed = {s.name: entry for s, entry in netview.described(changed).symbols}
    assert fixed["fill_to"]["description"].startswith("RENAMED "), fixed["fill_to"]
    before = {s.name: e for s, e in described.symbols}["fill_to"]["description"]
    assert not before.startswith("RENAMED "), before
    others = [compile_text(TRANSPORT.read_text() + f"\n# variant {n}\n", str(TRANSPORT))
              for n in range(2)]
    for net in others:
        netview.prewarm(net)
    assert [key[0] for key in netview._cache] == [net.program_hash for net in others]
    assert netview.KEPT == 2
    # No net in the cache: describing one takes no lasting reference to it.
    net = compile_text(TRANSPORT.read_text() + "\n# let go\n", str(TRANSPORT))
    references = sys.getrefcount(net)
    netview.prewarm(net)
    assert (net.program_hash, id(net.io)) in netview._cache
    assert sys.getrefcount(net) == references


def test_a_retain_capture_is_handed_to_its_writer_after_the_scan(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """The capture is taken at the scan boundary (consistent) and given to the writer thread
    in the slack: woken inside the scan, the writer took the interpreter lock from it to
    encode, and every capture's scan ran ~1.3 ms at a 1 ms period (a slot a second)."""
    from softplc.runtime.retain.writer import RetainWriter

    woken: list[bool] = []
    loop: WatchedLoop | None = None
    submit = RetainWriter.submit

    def watched(self: RetainWriter, cap: Any, later: bool = False) -> None:
        if later:  # held until the slack
            submit(self, cap, later)
            return
        if loop is not None:  # the writer thread is woken now
            woken.append(loop.in_scan)
        submit(self, cap)
    monkeypatch.setattr(RetainWriter, "submit", watched)
    loop = WatchedLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                                  period_ns=10_000_000, state_dir=str(tmp_path / "state"),
                                  retain_interval_ns=50_000_000, max_scans=40), None, None)
    assert loop.retain is not None
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    thread.join(30)
    assert not thread.is_alive()
    assert len(woken) >= 3, woken  # 0.4 s of scans, a capture every 50 ms
    assert not any(woken), f"woken inside a scan: {woken}"
    assert loop.retain.writes >= 3  # and written


def test_the_boot_program_of_a_download_is_encoded_in_the_compile_process(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """With a state dir, the download's boot program file comes encoded from the compile
    process; the scan process's helper thread only writes and syncs it (JSON-escaping a
    500 KB program there held the scan's interpreter lock 1-1.5 ms at a time)."""
    from softplc.program import boot

    encoded_here: list[str] = []
    pieces = boot._json_pieces

    def watched(program: boot.BootProgram) -> Any:
        encoded_here.append(program.program_hash)
        return pieces(program)
    monkeypatch.setattr(boot, "_json_pieces", watched)
    state = tmp_path / "state"
    _, new_hash, _ = _online_change(monkeypatch, state)
    kept = boot.load(state)
    assert kept is not None and kept.program_hash == new_hash
    assert kept.text.endswith("# the same net, another text\n")
    assert new_hash not in encoded_here, "encoded in the scan process"
