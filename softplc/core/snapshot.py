"""Values that cross the scan boundary: the published snapshot and journaled HMI writes.

Owns: Status (what the Modbus status block and `softplc status` show), Snapshot, HmiWrite,
commands and their replies, and the contract between the scan process and the services that
read and command it (the Modbus slave, the HTTP API, OPC UA): SnapshotSource and the
exceptions its implementations and the command channel raise (SnapshotUnavailable,
ChannelFull, NotQueued, NoReply), so that both sides import them from here.
Does not know: shared memory, pipes, sockets, Modbus function codes, the clock (an age is
computed from a `now_ns` the caller read).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Protocol

from softplc.core.errors import SoftplcError
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
    fault_code: int = 0  # a FaultCode (core/problems.py)
    period_us: int = 0
    forced: int = 0  # how many symbols are forced (docs/design.md section 10)
    waiting_for_io: bool = False  # a device has not delivered its first input image (issue 26)
    marking_kept: bool = False  # STOPPED by a stop: Stage.SUSPENDED, not READY (issue 29)
    # About the snapshot, not the PLC (so not part of equality): CLOCK_MONOTONIC when the scan
    # process published it (0: never), and a reader's verdict that it is older than the PLC's
    # cycle allows (the scan process is frozen or dead).
    published_ns: int = field(default=0, compare=False)
    stale: bool = field(default=False, compare=False)


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
    `program_path` names it in messages and resolves its relative `io_image:`/subnet paths.
    `deadline_ns` (CLOCK_MONOTONIC, shared by every process of the machine; 0: none) is the
    last moment the scan may apply it: later, it is refused as expired and never applied, so
    a sender that gave up waiting never sees it happen afterwards."""

    id: int
    command: Command
    program_text: str | None = None
    program_path: str | None = None
    online: bool = False
    symbol: str | None = None  # FORCE/UNFORCE (docs/design.md section 10); UNFORCE None: all
    value: int = 0  # FORCE
    deadline_ns: int = 0
    replace: bool = False  # a download of another program while RUNNING may replace it
    bundle: bytes | None = None  # a download as a bundle (softplc/program/bundle.py zip)
    dry_run: bool = False  # a download answered with its plan, never applied


# The head of every refused download's message, whoever refuses it (the scan process, or a
# service that finds the request unusable before sending it).
DOWNLOAD_REFUSED = "download refused"


class Refusal(Enum):
    """Why a command was not applied, as data: the services choose their answer (an HTTP
    status, an OPC UA status code) from it, never from the message's text."""

    PROGRAM = "program"  # the download does not compile: problems at FILE:LINE
    ANALYSIS = "analysis"  # the analysis gate refused it (--verify refuse)
    DEVICE = "device"  # its devices cannot be opened
    COMPILER = "compiler"  # the compile process died, ran out of time, or failed inside
    BOOT = "boot"  # it cannot be kept as the boot program
    SIZES = "sizes"  # its image sizes differ from the runtime's
    WITHDRAWN = "withdrawn"  # a stop or kill sent after it came first
    STATE = "state"  # the lifecycle table or the online-change rules refuse it in this state
    EXPIRED = "expired"  # drained after its deadline, never applied
    SIGNATURE = "signature"  # not signed by a trusted key (the service refuses it, unsent)

    @property
    def of_program(self) -> bool:
        """A refusal of the downloaded program itself, not of the moment it came."""
        return self in _PROGRAM_REFUSALS


_PROGRAM_REFUSALS = frozenset({Refusal.PROGRAM, Refusal.ANALYSIS, Refusal.DEVICE,
                               Refusal.COMPILER, Refusal.BOOT, Refusal.SIZES,
                               Refusal.SIGNATURE})


@dataclass(frozen=True, slots=True)
class CommandReply:
    """`ok`: applied. Not ok: refused (the state unchanged; `refusal` says why, `problems`
    lists every problem of a refused program), or `expired`: drained after its deadline and
    never applied."""

    id: int
    ok: bool
    message: str
    state: PlcState
    expired: bool = False
    detail: dict[str, object] | None = None  # a dry run's plan (core/online.py describe)
    refusal: Refusal | None = None
    problems: tuple[str, ...] = ()


class SnapshotSource(Protocol):
    """Where the communication process reads the last published scan from."""

    def latest(self) -> Snapshot:
        """The last complete publish; SnapshotUnavailable when none can be read now."""
        ...


def age_ns(snapshot: Snapshot, now_ns: int) -> int:
    """Nanoseconds from the publish of `snapshot` to `now_ns` (CLOCK_MONOTONIC, the same for
    every process of the machine); -1 when it was never published."""
    published = snapshot.status.published_ns
    return now_ns - published if published else -1


class SnapshotUnavailable(SoftplcError, RuntimeError):
    """No consistent snapshot could be read: the writer stayed mid-publish (stuck or dead)."""


class ChannelFull(SoftplcError):
    """A command or HMI write was refused at once because the scan process has not drained its
    queue (the scan is overloaded or not running), or no reply lane is free. Nothing of it is
    applied. The HTTP API answers 503, the Modbus slave 06 (busy), OPC UA
    BadResourceUnavailable."""


class NotQueued(SoftplcError, TimeoutError):
    """A command that could not be put in the queue in time: the scan process will never see
    it whole, so it is never applied."""


class NoReply(SoftplcError, TimeoutError):
    """A command queued whose reply did not come in time: it may still be decided later (but
    never applied after its deadline, if it has one)."""
