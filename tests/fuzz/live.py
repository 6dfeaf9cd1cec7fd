"""A live PLC for fuzz and security tests: the real ScanLoop, Channel, StatusBoard and
shared-memory snapshot, scanned by a thread on virtual time (10 ms per scan, ~2 ms of real
time each), with a program root of the test's choosing."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

from softplc.core.image import ImageSizes
from softplc.core.lifecycle import Command
from softplc.core.snapshot import CommandReply, CommandRequest
from softplc.runtime.loop import LoopConfig
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.shm import SnapshotReader, SnapshotWriter
from tests.api.conftest import PERIOD_NS, ScanThread
from tests.support import eventually

__all__ = ["LivePlc", "eventually"]


class LivePlc:
    """Context manager: the scan side of a PLC running `program` (started) under `root`."""

    def __init__(self, root: Path, program: Path | None = None, start: bool = True) -> None:
        self.channel = Channel()
        self.writer = SnapshotWriter.create(ImageSizes())
        self.board = StatusBoard.create(f"softplc-fuzz-{uuid.uuid4().hex[:12]}")
        self.reader = SnapshotReader.attach(self.writer.name, self.writer.sizes)
        config = LoopConfig(program=str(program) if program else None, start=start,
                            root=str(root), period_ns=PERIOD_NS)
        self.scan = ScanThread(self.channel, self.writer, self.board, config)
        self.loop = self.scan.loop
        self._ids = 0

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
        self.scan.__enter__()
        eventually(lambda: self.reader.latest().seq > 0)
        return self

    def __exit__(self, *exc: object) -> None:
        self.scan.__exit__()
        self.reader.close()
        self.writer.close()
        self.writer.unlink()
        self.board.close()
