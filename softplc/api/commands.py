"""Program commands with a contract, as the communication side keeps them.

Owns: command ids, deadlines, the outcome of every recent command (pending, applied, refused,
expired, unknown), late replies, and idempotency keys (a retry with the same key never sends
the command twice). Does not know: HTTP, the channel's framing, what a command does.

The contract (docs/api.md): a command is applied and acknowledged, refused, or expired. The
scan process refuses, unapplied, a command drained after its deadline; so a sender that gave
up waiting can truthfully say "pending" with the id, and the outcome is fixed by then.
"""

from __future__ import annotations

import enum
import itertools
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from typing import Any, Final

from softplc.core.snapshot import CommandReply, CommandRequest

COMMAND_DEADLINE_S: Final = 5.0  # lifecycle commands: applied within this, or never
DOWNLOAD_DEADLINE_S: Final = 60.0  # a download compiles first (a 10,000-transition net: ~2 s)
REPLY_GRACE_S: Final = 1.0  # a command drained just before its deadline answers soon after
UNKNOWN_AFTER_S: Final = 10.0  # no reply this long after the deadline: the scan process died
KEEP: Final = 1024  # outcomes and idempotency keys remembered


class Outcome(enum.Enum):
    PENDING = "pending"
    APPLIED = "applied"
    REFUSED = "refused"
    EXPIRED = "expired"
    UNKNOWN = "unknown"  # no reply ever came (scan process restarted); never applied late


@dataclass(frozen=True, slots=True)
class Record:
    id: int
    command: str
    deadline_ns: int
    outcome: Outcome = Outcome.PENDING
    message: str = ""
    state: str = ""

    def as_dict(self) -> dict[str, Any]:
        record = self.settled()
        return {"id": record.id, "command": record.command, "status": record.outcome.value,
                "message": record.message, "state": record.state or None,
                "deadline_in_ms": round((record.deadline_ns - time.monotonic_ns()) / 1e6)}

    def settled(self) -> Record:
        """This record, or UNKNOWN when its reply is overdue beyond any doubt."""
        overdue_ns = time.monotonic_ns() - self.deadline_ns
        if self.outcome is Outcome.PENDING and overdue_ns > UNKNOWN_AFTER_S * 1e9:
            return replace(self, outcome=Outcome.UNKNOWN, message=(
                "no reply from the scan process (it may have restarted); the command was "
                "not applied after its deadline, and will not be"))
        return self


class CommandBook:
    """Thread-safe: replies arrive on the channel's reply thread."""

    def __init__(self) -> None:
        # Random start: ids of a restarted communication process never meet older ones.
        self._ids = itertools.count(secrets.randbits(40) + 1)
        self._records: OrderedDict[int, Record] = OrderedDict()
        self._keys: OrderedDict[str, int] = OrderedDict()
        self._lock = threading.Lock()

    def request(self, command: Any, deadline_s: float, key: str | None = None,
                **fields: Any) -> CommandRequest:
        """A new request with its id and deadline, recorded as pending (under `key`)."""
        deadline_ns = time.monotonic_ns() + int(deadline_s * 1e9)
        request = CommandRequest(next(self._ids), command, deadline_ns=deadline_ns, **fields)
        with self._lock:
            self._remember(self._records, request.id, Record(request.id, command.value,
                                                              deadline_ns))
            if key is not None:
                self._remember(self._keys, key, request.id)
        return request

    def by_key(self, key: str) -> Record | None:
        with self._lock:
            command_id = self._keys.get(key)
            record = self._records.get(command_id) if command_id is not None else None
        return record.settled() if record is not None else None

    def get(self, command_id: int) -> Record | None:
        with self._lock:
            record = self._records.get(command_id)
        return record.settled() if record is not None else None

    def settle(self, reply: CommandReply) -> Record | None:
        """Record a reply (in time or late); returns the updated record."""
        outcome = (Outcome.APPLIED if reply.ok else
                   Outcome.EXPIRED if reply.expired else Outcome.REFUSED)
        with self._lock:
            record = self._records.get(reply.id)
            if record is None:
                return None
            record = replace(record, outcome=outcome, message=reply.message,
                             state=reply.state.name)
            self._records[reply.id] = record
        return record

    def drop(self, command_id: int, message: str) -> None:
        """A command that never reached the queue: refused, never applied."""
        with self._lock:
            record = self._records.get(command_id)
            if record is not None:
                self._records[command_id] = replace(record, outcome=Outcome.REFUSED,
                                                    message=message)

    @staticmethod
    def _remember(table: OrderedDict[Any, Any], key: Any, value: Any) -> None:
        table[key] = value
        while len(table) > KEEP:
            table.popitem(last=False)
