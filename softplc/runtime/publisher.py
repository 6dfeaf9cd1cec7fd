"""What a scan loop shows the other processes, and when: the snapshot (the process image and
the scan's status, after every scan) and the status board (the status document: about every
50 ms, and at once for a new program or a pause).

Owns: when each is due; their order (a new program's board before the snapshot that carries
its hash: a service that sees the hash finds the program's symbols, hmi/eng.py); and, on a
paced loop, the board held for the scan's slack (`out`, runtime/loop.py `_slack`, before the
scan's replies: a client told "applied" reads the new program's board), with the snapshot
of a scan that swapped programs behind it. Scanned by hand (tests): both at once.
Why after the scan: the board is a view for people and services, not the scan's I/O. Its
document and its JSON took 0.3-0.7 ms of a 1 ms scan in the scan process (per-call timers,
issue 40 item 8): every refresh scan ran 0.6-0.9 ms, and the swap scan of an online change,
0.6-1.2 ms, missed the next slot whenever it ran past 1 ms. The snapshot of any other scan
is published in the scan (~25 us): it is what Modbus and the HMI read of that scan.
Does not know: what a document holds (statusdoc.py), the scan.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from softplc.core.plc import Plc
from softplc.core.snapshot import Status
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.shm import SnapshotWriter

BOARD_EVERY_NS = 50_000_000  # the board's refresh, about


class Publisher:
    """`refreshing()` says whether this scan refreshes the board (the loop's timing summary
    first); `scanned()` after each scan; `out()` in its slack."""

    def __init__(self, writer: SnapshotWriter | None, board: StatusBoard | None,
                 period_ns: int, document: Callable[[], dict[str, Any]],
                 status: Callable[[], Status]) -> None:
        self.writer, self.board = writer, board
        self.every = max(1, BOARD_EVERY_NS // period_ns)  # scans between the board's refreshes
        self._document, self._status = document, status
        self._program: str | None = None  # the program hash the board was published with
        self._pause: object = None  # the pause the board shows (core/breakpoints.py)
        self._plc: Plc | None = None
        self._board_due = self._snapshot_due = False

    def refreshing(self, scans: int) -> bool:
        """The scan after `scans` scans refreshes the board. Counted in cycles, not scans: a
        paused PLC counts no scans (docs/debug.md)."""
        return (scans + 1) % self.every == 0

    def scanned(self, plc: Plc, refresh: bool, later: bool) -> None:
        """After a scan: the snapshot now, unless the program changed (then behind its
        board); the board when due (`refresh`: what `refreshing` said of this scan, or a new
        program, or a pause). Held for `out()` when `later` (a paced loop)."""
        board = refresh
        program = net.program_hash if (net := plc.net) is not None else None
        swapped = self.board is not None and program != self._program
        if swapped:
            self._program, board = program, True
        # A pause on the board at once: the supervisor reads it if this process dies.
        if (pause := plc.debug.pause) is not self._pause:
            self._pause, board = pause, True
        self._plc = plc
        self._board_due |= board
        self._snapshot_due |= swapped
        if not swapped and self.writer is not None:
            self.writer.publish(plc.image, self._status())
        if not later:
            self.out()

    def out(self) -> None:
        """What is held: the board, then the snapshot behind it."""
        board_due, snapshot_due, plc = self._board_due, self._snapshot_due, self._plc
        self._board_due = self._snapshot_due = False
        if board_due and self.board is not None:
            self.board.publish(self._document())
        if snapshot_due and self.writer is not None and plc is not None:
            self.writer.publish(plc.image, self._status())
