"""The scan process's entry point: signals, the watch on the supervisor, shared memory
attached, the loop built and run, "safe" said to the supervisor once the devices confirmed
the safe outputs at a stop, everything let go at the end.

Owns: the scan process's exit codes (0 stopped, 3 state directory busy, 4 cannot start).
Does not know: what a scan does (runtime/loop.py).
"""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import sys
import threading
from collections.abc import Iterator

from softplc.core.problems import ProgramError
from softplc.runtime.config import LoopConfig
from softplc.runtime.loop import ScanLoop
from softplc.runtime.realtime import apply, share_interpreter
from softplc.runtime.retain.writer import StateDirBusy
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.procs import Flag as Event
from softplc.runtime.shared.procs import ReadySignal
from softplc.runtime.shared.shm import SnapshotWriter


def scan_process_main(config: LoopConfig, channel: Channel, shm_name: str, board_name: str,
                      ready: ReadySignal, stop: Event) -> None:
    """Entry point of the scan process. SIGINT is the parent's business: it sets `stop`.
    Exit codes: 0 stopped, 3 state directory busy, 4 cannot start (program, devices)."""
    from softplc.runtime.shared.procs import (
        die_with_parent,
        exit_now,
        name_process,
        once,
        supervisor_pid,
    )

    name_process()  # softplc-scan (Supervisor.start_scan)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, once(stop.set))
    die_with_parent()
    parent = supervisor_pid()

    def watch_parent() -> None:
        while not stop.wait(0.5):
            if os.getppid() != parent:
                stop.set()  # the supervisor is gone: go safe and end

    threading.Thread(target=watch_parent, name="watch-parent", daemon=True).start()
    realtime = apply(config.realtime)  # after the watcher: it keeps normal scheduling
    realtime += ", " + share_interpreter(config.period_ns)
    with attached(config, shm_name, board_name) as (writer, board):
        try:
            loop = ScanLoop(config, channel, writer, board=board)
            loop.realtime = realtime
        except StateDirBusy as exc:
            print(f"softplc: {exc}", file=sys.stderr)
            raise SystemExit(3) from None
        except (ProgramError, ValueError, OSError) as exc:
            print(f"softplc: cannot start the scan: {exc}", file=sys.stderr)
            raise SystemExit(4) from None
        writer.publish(loop.runner.plc.image, loop.status())
        board.publish(loop.document())
        gc.collect()  # before the first scan, not during one; then keep what start-up built
        gc.freeze()  # out of every later collection (real-time practice, see Preparer.prepare)
        ready.set()
        loop.run(stop, safe=lambda: ready.say(ReadySignal.SAFE))
    exit_now(0)  # outputs safe, retain written, segments let go: nothing left to tear down


@contextlib.contextmanager
def attached(config: LoopConfig, shm_name: str,
             board_name: str) -> Iterator[tuple[SnapshotWriter, StatusBoard]]:
    """The snapshot segment and the status board a scan process publishes into. The
    supervisor created both (it owns them: they outlive a scan process); one created here
    because it was missing is removed again at the end."""
    writer, own_segment = SnapshotWriter.open_or_create(config.sizes, shm_name)
    board, own_board = StatusBoard.open_or_create(board_name)
    try:
        yield writer, board
    finally:
        writer.close()
        if own_segment:
            writer.unlink()
        if own_board:
            board.close()
        else:
            board.detach()
