"""Audit records written off the Modbus loop, and the audit of the plain port's writes.

Owns: AuditWriter (records, or jobs that end in one, done by one thread in the order they
are handed over, so that the loop never waits for the trail's lock or fsync; how many wait),
and WriteAudit: each write on the plain Modbus TCP port handed to coalesce.py's rule from
the slave's loop, a timer closing its windows while any is open, every count left written
at stop. While the thread lags (MAX_PENDING records waiting), writes are counted, not
recorded one by one, and windows stay open: nothing is lost, the loop is never held.
Does not know: the trail's format and files (security/audit.py, handed in as AuditSink),
sockets, Modbus framing.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Final, Protocol

from softplc.hmi.coalesce import WINDOW_S, Coalescer, describe_write

log = logging.getLogger(__name__)

MAX_PENDING: Final = 256  # records handed to the thread and not written yet
TICK_S: Final = 1.0  # how often open windows are looked at (at most; less with short windows)


class AuditSink(Protocol):
    """security/audit.py's AuditTrail: appends one record (blocking, it fsyncs)."""

    def append(self, entry: dict[str, Any]) -> object: ...


class AuditWriter:
    """One thread writing records in order; call from one asyncio loop, `close()` at the end.
    `what` names the writer in log lines."""

    def __init__(self, sink: AuditSink, max_pending: int = MAX_PENDING,
                 what: str = "Modbus") -> None:
        self._sink = sink
        self._max_pending = max_pending
        self._what = what
        self.pending = 0
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="modbus-audit")

    def has_room(self) -> bool:
        return self.pending < self._max_pending

    def record(self, entry: dict[str, Any]) -> None:
        self.submit(lambda: self.append(entry))

    def submit(self, job: Callable[[], object]) -> None:
        """Run `job` (blocking file work) in the writer's thread after those before it."""
        self.pending += 1
        future = asyncio.get_running_loop().run_in_executor(self._executor, job)
        future.add_done_callback(self._done)

    def append(self, entry: dict[str, Any]) -> None:
        """In the thread: one record; a failure is logged, the action it records stands."""
        try:
            self._sink.append(entry)
        except OSError as exc:
            log.error("audit record of a %s %s not written: %s", self._what, entry["action"],
                      exc)

    async def close(self) -> None:
        """Wait for everything handed over so far to be written."""
        await asyncio.to_thread(self._executor.shutdown, True)

    def _done(self, future: asyncio.Future[object]) -> None:
        self.pending -= 1
        if not future.cancelled() and future.exception() is not None:
            log.error("%s audit record failed", self._what, exc_info=future.exception())


@dataclass(frozen=True, slots=True)
class WritesAudited:
    """How a plain slave audits its writes: the trail and the write policy's name (open,
    symbols, none: docs/modbus.md), which decides the role written (`none`: viewer, the
    others: operator, as anyone reaching the port writes what the policy allows)."""

    sink: AuditSink
    policy: str
    window_s: float = WINDOW_S


class WriteAudit:
    """The audit of one plain slave's writes, on its loop. `name_of(table, address)` gives
    the IEC address of a Modbus one (the register map's), or None."""

    def __init__(self, config: WritesAudited,
                 name_of: Callable[[str, int], str | None] | None = None,
                 max_pending: int = MAX_PENDING) -> None:
        role = "viewer" if config.policy == "none" else "operator"
        self._coalescer = Coalescer({"user": None, "role": role, "via": "anonymous"},
                                    {"policy": config.policy}, window_s=config.window_s)
        self._writer = AuditWriter(config.sink, max_pending)
        self._name_of = name_of
        self._tick_s = min(TICK_S, config.window_s / 4)
        self._timer: asyncio.TimerHandle | None = None

    @property
    def pending(self) -> int:
        """Records handed to the writer's thread and not written yet."""
        return self._writer.pending

    def write(self, peer: str, unit: int, request: bytes, reply: bytes, now_s: float) -> None:
        """A write request (PDU) and its reply (PDU), answered at `now_s` (the loop's time)."""
        code = reply[1] if reply[0] & 0x80 and len(reply) > 1 else 0
        described = describe_write(request)
        if self._name_of is not None and isinstance(described.get("address"), int):
            iec = self._name_of(str(described["table"]), described["address"])
            if iec is not None:
                described["iec"] = iec
        entry = self._coalescer.note(peer, unit, described, code, now_s,
                                     self._writer.has_room())
        if entry is not None:
            self._writer.record(entry)
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(self._tick_s, self._tick)

    def _tick(self) -> None:
        loop = asyncio.get_running_loop()
        self._timer = None
        if self._writer.has_room():
            for entry in self._coalescer.due(loop.time(), time.time()):
                self._writer.record(entry)
        if self._coalescer.open:
            self._timer = loop.call_later(self._tick_s, self._tick)

    async def close(self) -> None:
        """Write every count still open and wait until the trail has them (at stop)."""
        loop = asyncio.get_running_loop()
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for entry in self._coalescer.drain(loop.time(), time.time()):
            self._writer.record(entry)
        await self._writer.close()
