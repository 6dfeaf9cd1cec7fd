"""Fixtures: a real Channel, StatusBoard and shared-memory snapshot, served by a real
ScanLoop driven by a test thread on virtual time, and the ApiServer on its own asyncio loop
in another thread, bound to 127.0.0.1 port 0."""

from __future__ import annotations

import asyncio
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from softplc.api.server import ApiServer
from softplc.core.image import ImageSizes
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.shm import SnapshotReader, SnapshotWriter

ROOT = Path(__file__).resolve().parents[2]
PERIOD_NS = 10_000_000


class ScanThread:
    """The scan side: a real ScanLoop whose scan_once runs every ~2 ms of real time on a
    virtual clock (10 ms per scan), publishing the snapshot and the board after each scan."""

    def __init__(self, channel: Channel, writer: SnapshotWriter, board: StatusBoard,
                 config: LoopConfig | None = None) -> None:
        config = config or LoopConfig(root=str(ROOT), period_ns=PERIOD_NS)
        self.loop = ScanLoop(config, channel, writer, board=board)
        self._writer = writer
        self._board = board
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="test-scan", daemon=True)

    def _run(self) -> None:
        now_ns = 0
        while not self._stop.is_set():
            self.loop.scan_once(now_ns)
            self._writer.publish(self.loop.runner.plc.image, self.loop.status())
            self._board.publish(self.loop.document())
            now_ns += PERIOD_NS
            time.sleep(0.002)

    def __enter__(self) -> ScanThread:
        if self.loop.compiler is not None:
            self.loop.compiler.start()  # as ScanLoop.run does: ready before the first download
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)
        self.loop.runner.close()
        if self.loop.compiler is not None:  # downloads compiled in a real compile process
            self.loop.compiler.close()


@dataclass
class Plc:
    channel: Channel
    reader: SnapshotReader
    board: StatusBoard
    writer: SnapshotWriter


@pytest.fixture
def plc_parts() -> Iterator[Plc]:
    """Channel, snapshot and board with nothing on the scan side yet."""
    channel = Channel()
    writer = SnapshotWriter.create(ImageSizes())
    board = StatusBoard.create(f"softplc-test-{uuid.uuid4().hex[:12]}")
    reader = SnapshotReader.attach(writer.name, writer.sizes)
    try:
        yield Plc(channel, reader, board, writer)
    finally:
        channel.close()
        reader.close()
        writer.close()
        writer.unlink()
        board.close()


@pytest.fixture
def scan(plc_parts: Plc) -> Iterator[ScanThread]:
    with ScanThread(plc_parts.channel, plc_parts.writer, plc_parts.board) as thread:
        yield thread


class ServerThread:
    """An ApiServer on its own asyncio loop in a thread."""

    def __init__(self, server: ApiServer) -> None:
        self.server = server
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="test-api",
                                        daemon=True)

    def call(self, coro: Any, timeout_s: float = 10.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    @staticmethod
    async def _drain() -> None:
        """Let connection handlers that stop() cancelled finish before the loop closes."""
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        for task in others:
            task.cancel()
        await asyncio.gather(*others, return_exceptions=True)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server.bound_port}"

    def __enter__(self) -> ServerThread:
        self._thread.start()
        self.call(self.server.start())
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.call(self.server.stop())
            self.call(self._drain())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(5)
            self.loop.close()


def make_server(plc: Plc, state_dir: Path, **kwargs: Any) -> ServerThread:
    # A command's deadline: generous, because the test's scan thread shares a loaded
    # machine (a command that expires before the scan takes it fails the test that sent it).
    server = ApiServer(plc.channel, plc.reader, plc.board, port=0, state_dir=state_dir,
                       command_timeout_s=kwargs.pop("command_timeout_s", 30.0), **kwargs)
    return ServerThread(server)


@pytest.fixture
def api(plc_parts: Plc, scan: ScanThread, tmp_path: Path) -> Iterator[ServerThread]:
    """The service in front of a live (virtual-time) scan loop, no token."""
    with make_server(plc_parts, tmp_path / "state") as handle:
        yield handle
