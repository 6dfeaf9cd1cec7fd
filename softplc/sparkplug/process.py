"""The Sparkplug process (`softplc-spb`): one edge node over the published snapshot, the
status board and the command channel, started and restarted alone by the supervisor like
the other service processes (runtime/supervise/supervisor.py).

Owns: attaching the snapshot and the board, the door's audit trail in STATE_DIR, the loop
(the node's step every STEP_S, the door's outcomes into the status metric), the niceness
(NICE, as OPC UA: reporting yields to the scan and to the HMI doors), and the stop: SIGTERM
ends the loop, an NDEATH goes out before DISCONNECT, then the process exits.
Does not know: MQTT details (node.py), decisions (door.py).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import time
from typing import Any, Final

from softplc.core.image import ImageSizes
from softplc.core.snapshot import SnapshotUnavailable
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.fresh import FreshSource
from softplc.runtime.shared.procs import (
    Flag,
    die_with_parent,
    exit_now,
    name_process,
    once,
    supervisor_pid,
)
from softplc.runtime.shared.shm import SnapshotReader
from softplc.security.audit import AuditTrail
from softplc.sparkplug.config import SparkplugConfig
from softplc.sparkplug.door import Door
from softplc.sparkplug.node import EdgeNode, Reading

log = logging.getLogger("softplc.sparkplug")

STEP_S: Final = 0.02  # how long one step waits for the socket
# The status board (symbols, fault reason: a JSON document) is read again at most this often,
# or at once when the snapshot names another program; state and scan count come from the
# snapshot of every read (the board is a JSON document of every symbol: BENCHMARKS.md,
# Sparkplug, for what this saved).
BOARD_S: Final = 0.5
NICE: Final = 10
NAME: Final = "softplc-spb"


class Reader:
    """The status board (cached for BOARD_S) and the latest snapshot, for the node."""

    def __init__(self, board: StatusBoard, source: FreshSource) -> None:
        self._board, self._source = board, source
        self._document: dict[str, Any] = {}
        self._read_s = float("-inf")

    def read(self) -> Reading:
        snapshot = None
        with contextlib.suppress(SnapshotUnavailable):
            snapshot = self._source.latest()
        now_s = time.monotonic()
        hash_now = snapshot.status.program_hash if snapshot is not None else None
        if now_s - self._read_s >= BOARD_S or (
                hash_now is not None and hash_now != (self._document.get("program_hash") or "")):
            with contextlib.suppress(TimeoutError):
                self._document = self._board.read()
                self._read_s = now_s
        if snapshot is None:
            return self._document, None
        status = snapshot.status
        return {**self._document, "state": status.state.name,
                "scan_count": status.scan_count}, snapshot.image


def process_main(config: SparkplugConfig, channel: Channel, shm_name: str, board_name: str,
                 ready: Flag, stop: Flag) -> None:
    name_process(NAME)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, once(stop.set))
    die_with_parent()
    mapping = SnapshotReader.attach(shm_name, config.sizes or ImageSizes())
    source = FreshSource(mapping)
    board = StatusBoard.attach(board_name)
    door = Door(config, channel, source, AuditTrail(config.state_dir), board.read)

    node = EdgeNode(config, Reader(board, source).read, door.submit)
    os.nice(NICE)
    ready.set()  # serving from now on: the broker may be away, the node keeps trying
    parent = supervisor_pid()
    try:
        while not stop.is_set() and os.getppid() == parent:
            node.step(STEP_S)
            lines = door.outcomes()
            if lines and node.report is not None:
                node.report.status = lines[-1]
                for line in lines:
                    log.info("Sparkplug command %s", line)
    finally:
        node.close()
        door.close()
        mapping.close()
        board.close()
    exit_now(0)
