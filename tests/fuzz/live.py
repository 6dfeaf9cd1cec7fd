"""A live PLC for fuzz and security tests: the real ScanLoop, Channel, StatusBoard and
shared-memory snapshot, scanned by a thread on virtual time (10 ms per scan, ~2 ms of real
time each), with a program root of the test's choosing."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from softplc.core.image import ImageSizes
from softplc.core.lifecycle import Command
from softplc.core.snapshot import CommandReply, CommandRequest
from softplc.runtime.board import StatusBoard
from softplc.runtime.channel import Channel
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.shm import SnapshotReader, SnapshotWriter

PERIOD_NS = 10_000_000
T = TypeVar("T")


def eventually(probe: Callable[[], T | None], timeout_s: float = 5.0) -> T:
    deadline = time.monotonic() + timeout_s
    while True:
        result = probe()
        if result:
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s")
        time.sleep(0.005)


class LivePlc:
    """Context manager: the scan side of a PLC running `program` (started) under `root`."""

    def __init__(self, root: Path, program: Path | None = None, start: bool = True) -> None:
        self.channel = Channel()
        self.writer = SnapshotWriter.create(ImageSizes())
        self.board = StatusBoard.create(f"softplc-fuzz-{uuid.uuid4().hex[:12]}")
        self.reader = SnapshotReader.attach(self.writer.name, self.writer.sizes)
        config = LoopConfig(program=str(program) if program else None, start=start,
                            root=str(root), period_ns=PERIOD_NS)
        self.loop = ScanLoop(config, self.channel, self.writer, board=self.board)
        self._ids = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fuzz-scan", daemon=True)

    def _run(self) -> None:
        now_ns = 0
        while not self._stop.is_set():
            self.loop.scan_once(now_ns)
            self.writer.publish(self.loop.runner.plc.image, self.loop.status())
            self.board.publish(self.loop.document())
            now_ns += PERIOD_NS
            time.sleep(0.002)

    def command(self, command: Command, text: str | None = None, name: str | None = None,
                online: bool = False) -> CommandReply:
        self._ids += 1
        request = CommandRequest(self._ids, command, program_text=text, program_path=name,
                                 online=online)
        return self.channel.send_command(request, 10.0)

    def document(self) -> dict[str, Any]:
        """The board as the scan published it after its latest scan."""
        return self.board.read()

    def settled(self) -> dict[str, Any]:
        """The board after at least two more scans (so that earlier commands show)."""
        first = self.reader.latest().seq
        eventually(lambda: self.reader.latest().seq >= first + 2)
        return self.document()

    def __enter__(self) -> LivePlc:
        self._thread.start()
        eventually(lambda: self.reader.latest().seq > 0)
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self.loop.runner.close()
        self.reader.close()
        self.writer.close()
        self.writer.unlink()
        self.board.close()
