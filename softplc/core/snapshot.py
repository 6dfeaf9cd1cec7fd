"""Values that cross the scan boundary: the published snapshot and journaled HMI writes.

Owns: Status (what the Modbus status block and `softplc status` show), Snapshot, HmiWrite.
Does not know: shared memory, sockets, Modbus function codes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from softplc.core.image import Address, ProcessImage
from softplc.core.lifecycle import Command, PlcState


@dataclass(frozen=True, slots=True)
class Status:
    state: PlcState = PlcState.EMPTY
    scan_count: int = 0
    last_exec_us: int = 0
    max_exec_us: int = 0
    p99_lateness_us: int = 0
    overruns: int = 0
    program_hash: str = ""  # hex sha256 of the program text, "" when EMPTY
    fault_code: int = 0  # 0 none, 1 watchdog, 2 device
    period_us: int = 0
    forced: int = 0  # how many symbols are forced (DESIGN.md section 10)


@dataclass(frozen=True, slots=True)
class Snapshot:
    """One consistent view published after a scan: never half of one scan and half of another."""

    seq: int
    image: ProcessImage
    status: Status


@dataclass(frozen=True, slots=True)
class HmiWrite:
    """Consecutive values written by an HMI, starting at `address`; applied at the next scan
    start. Bits take 0/1, words 0..65535."""

    address: Address
    values: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class CommandRequest:
    """A program command sent to the scan process. `program_text` is the YAML of a download;
    `program_path` names it in messages and resolves its relative `io_image:`/subnet paths."""

    id: int
    command: Command
    program_text: str | None = None
    program_path: str | None = None
    online: bool = False
    symbol: str | None = None  # FORCE/UNFORCE (DESIGN.md section 10); UNFORCE None: all
    value: int = 0  # FORCE


@dataclass(frozen=True, slots=True)
class CommandReply:
    id: int
    ok: bool
    message: str
    state: PlcState


class SnapshotSource(Protocol):
    """Where the communication process reads the last published scan from."""

    def latest(self) -> Snapshot: ...
