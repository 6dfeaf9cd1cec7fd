"""The Sparkplug door: what a host's NCMD may do to the PLC, decided, applied and audited like
at every other door (issue 38).

Owns: a host's NCMD metric as an act: a symbol write (Act.WRITE) or a program command
(Node Control/Command = start, stop, resume or reset: its own act, and only with
`--sparkplug-commands`); the decision by `granted` for the door's configured role (MQTT says
nothing about who published a command: the broker's ACL decides who may publish NCMD, spec
5.11; this door gives each the role of --sparkplug-role, viewer by default = nothing); the
write policy (an input or `hmi_writable: false` symbol is refused, as is a write while the
board still describes another program), the typed check (core/present.py `accepted`, as the
HTTP API's); one audit record per command (iface "sparkplug"); the outcome as one line for
the `Node Control/Command Status` metric. Everything that blocks (the trail's fsync, a
command's reply) runs in one worker thread behind a bounded queue; a full queue refuses, and
whatever fails in the worker is a `failed` record and an answered outcome, never its end.
A command is judged against the running program: the last NBIRTH's metrics while that
program runs, else the status board's (a download while the broker was away, before the next
NBIRTH; an alias of the earlier birth is refused, a name is looked up anew).
Does not know: MQTT, topics, payload bytes.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import queue
import threading
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any, Final, Protocol

from softplc.core.image import split_registers
from softplc.core.lifecycle import Command
from softplc.core.present import ValueRefused, accepted
from softplc.core.snapshot import (
    ChannelFull,
    CommandReply,
    CommandRequest,
    HmiWrite,
    NoReply,
    NotQueued,
    SnapshotSource,
    SnapshotUnavailable,
)
from softplc.security.decide import Identity, granted
from softplc.security.roles import Act
from softplc.sparkplug import codec
from softplc.sparkplug.codec import Metric
from softplc.sparkplug.config import SparkplugConfig
from softplc.sparkplug.metrics import COMMAND, NODE, STATUS, Report, SymbolMetric

log = logging.getLogger(__name__)

MAX_WAITING: Final = 64  # commands queued for the worker; more are refused at once
COMMAND_TIMEOUT_S: Final = 5.0
PROGRAM_COMMANDS: Final = {c.value: c for c in (Command.START, Command.STOP, Command.RESUME,
                                                 Command.RESET)}
_FIRST_ID: Final = 2_000_000  # command ids that show Sparkplug in the trace


class Channel(Protocol):
    def send_hmi_write(self, write: HmiWrite) -> None: ...

    def send_command(self, request: CommandRequest, timeout_s: float = ...) -> CommandReply: ...


class AuditSink(Protocol):
    def append(self, entry: dict[str, Any]) -> object: ...


class Door:
    """Decides and applies hosts' commands in a worker thread; `outcomes()` (from the node's
    thread) returns the lines written since the last call."""

    def __init__(self, config: SparkplugConfig, channel: Channel, source: SnapshotSource,
                 audit: AuditSink, board: Callable[[], Mapping[str, Any]] | None = None
                 ) -> None:
        self.config = config
        self._board = board  # the status board now: the running program's symbols
        self.who = Identity(None, "policy", granted=config.role)
        self._channel, self._source, self._audit = channel, source, audit
        self._ids = itertools.count(_FIRST_ID)
        self._numbers = itertools.count(1)
        self._waiting: queue.Queue[Callable[[], None] | None] = queue.Queue(MAX_WAITING)
        self._done: queue.Queue[str] = queue.Queue()
        self.refused_busy = 0
        self._busy_unaudited = 0  # refused as busy, not yet in the audit trail
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._work, name="sparkplug-door", daemon=True)
        self._thread.start()

    def submit(self, report: Report | None, metric: Metric) -> None:
        """A host's NCMD metric (from the node's thread): queued for the worker. `report`:
        the last NBIRTH's metrics, None before the first one (every write is refused)."""
        try:
            self._waiting.put_nowait(lambda: self._handle(report, metric))
        except queue.Full:
            self.refused_busy += 1
            with self._lock:  # audited by the worker when it is free again
                self._busy_unaudited += 1
            self._done.put(f"#{next(self._numbers)} refused: more than {MAX_WAITING} "
                           "commands waiting")

    def outcomes(self) -> list[str]:
        lines: list[str] = []
        with contextlib.suppress(queue.Empty):
            while True:
                lines.append(self._done.get_nowait())
        return lines

    def close(self) -> None:
        with contextlib.suppress(queue.Full):
            self._waiting.put(None, timeout=1.0)
        self._thread.join(COMMAND_TIMEOUT_S + 1.0)

    def _work(self) -> None:
        while (job := self._waiting.get()) is not None:
            try:
                job()
            except Exception:  # a bug here must not end the door
                log.exception("Sparkplug command failed")
            self._audit_busy()
        self._audit_busy()

    def _audit_busy(self) -> None:
        """One record for the commands refused because the queue was full since the last."""
        with self._lock:
            count, self._busy_unaudited = self._busy_unaudited, 0
        if count:
            self._record("command", "refused", f"{count} command(s) refused: more than "
                         f"{MAX_WAITING} commands waiting", {"refused": count})

    # -- one command, in the worker ---------------------------------------------------------

    def _handle(self, report: Report | None, metric: Metric) -> None:
        """Decide, apply and audit one command. Whatever fails in it is audited too (outcome
        `failed`) and answered: the door goes on with the next."""
        target = metric.name if metric.name is not None else f"alias {metric.alias}" \
            if metric.alias is not None else "a metric without name or alias"
        try:
            action, target, outcome, why = self._decide(report, metric, target)
        except Exception as exc:  # a bug: audited and answered, never the door's end
            log.exception("Sparkplug command %s failed", target)
            action = "command" if metric.name == COMMAND else "write"
            outcome, why = "failed", f"the door failed ({type(exc).__name__}: {exc})"
        line = f"#{next(self._numbers)} {action} {target}: {outcome}" + (f" ({why})" if why
                                                                          else "")
        self._record(action, outcome, why or "ok",
                     {"metric": target, "value": _plain(metric.value)})
        self._done.put(line)

    def _view(self, report: Report) -> tuple[Report, bool]:
        """The metrics to judge a command against: the last NBIRTH's, or the current
        program's when another program runs since (a download while the broker was away: the
        node's next NBIRTH is not out yet). True: the view is not what the host was born."""
        if self._board is None:
            return report, False
        try:
            running = self._source.latest().status.program_hash
        except SnapshotUnavailable:
            return report, False  # _write refuses what it cannot check
        if running == str(report.document.get("program_hash") or ""):
            return report, False
        try:
            document = self._board()
        except TimeoutError:
            return report, False
        if str(document.get("program_hash") or "") != running:
            return report, False  # the board still describes another program
        return Report(document, 0.0), True

    def _decide(self, report: Report | None, metric: Metric, target: str
                ) -> tuple[str, str, str, str]:
        """(action, target, outcome, why) of one command."""
        symbol, program, born, stale = None, "", report is not None, False
        if report is not None:
            report, stale = self._view(report)
            if metric.name is None:  # by alias: a node metric's name, else a symbol's
                names = {alias: name for name, alias in report.node_alias.items()}
                if metric.alias in names:
                    metric = replace(metric, name=names[metric.alias])
            symbol = report.by_name.get(metric.name or "") if metric.name is not None \
                else report.by_alias.get(metric.alias or -1)
            program = str(report.document.get("program_hash") or "")
            target = metric.name or target  # a node metric's alias: its name
        if metric.name is None and metric.alias is None:
            action, outcome, why = "write", "refused", "the metric has no name and no alias"
        elif not born and metric.name != COMMAND:
            action, outcome, why = "write", "refused", f"no NBIRTH yet: {target} is not known"
        elif metric.name == COMMAND:
            action, outcome, why = self._program_command(metric.value)
        elif metric.name in NODE or metric.name == STATUS:
            action, outcome, why = "write", "refused", f"{target} is read only"
        elif stale and metric.name is None:
            action, outcome, why = "write", "refused", (
                "the program changed since the last NBIRTH: its aliases name other metrics "
                "now; send the name, or the alias of the next NBIRTH")
        elif symbol is None:
            action, outcome, why = "write", "refused", (
                f"no metric {target} in the running program" if stale
                else f"no metric {target} in the last NBIRTH")
        else:
            target = symbol.name
            action = "write"
            outcome, why = self._write(symbol, metric, program)
        return action, target, outcome, why

    def _record(self, action: str, outcome: str, status: str, detail: dict[str, Any]) -> None:
        entry = {"user": None, "role": self.config.role.label, "via": "policy",
                 "peer": f"{self.config.host}:{self.config.port}", "iface": "sparkplug",
                 "action": action, "outcome": outcome, "status": status, "detail": detail}
        try:
            self._audit.append(entry)
        except Exception as exc:  # a full disk, a value JSON cannot hold: logged, not fatal
            log.error("audit record of a Sparkplug %s not written: %s", action, exc)

    def _write(self, symbol: SymbolMetric, metric: Metric, program: str) -> tuple[str, str]:
        decision = granted(self.who, Act.WRITE)
        if not decision.allowed:
            return "denied", decision.reason() + " (--sparkplug-role)"
        if symbol.refusal is not None:
            return "refused", symbol.refusal
        try:  # as the Modbus slave: no write on a program nobody can see
            if self._source.latest().status.program_hash != program:
                return "refused", "the program changed: use the metrics of the next NBIRTH"
        except SnapshotUnavailable:
            return "refused", "the PLC's snapshot cannot be read: nothing is written"
        number = metric.value
        if metric.datatype is None and isinstance(number, int) and not isinstance(number, bool):
            number = codec.signed(symbol.datatype, number)  # by alias: the birth's datatype
        try:
            raw = accepted(symbol.type_name, number, symbol.name, symbol.scale)
        except ValueRefused as exc:
            return "refused", str(exc)
        address = symbol.address
        registers = (raw,) if address.is_bit else tuple(split_registers(raw, address.width))
        try:
            self._channel.send_hmi_write(HmiWrite(address, registers))
        except ChannelFull as exc:
            return "refused", str(exc)
        return "queued", ""

    def _program_command(self, value: object) -> tuple[str, str, str]:
        command = PROGRAM_COMMANDS.get(str(value).strip().lower())
        if command is None:
            return "command", "refused", (f"{value!r} is not one of "
                                          f"{', '.join(PROGRAM_COMMANDS)}")
        if not self.config.commands:
            return command.value, "refused", "program commands are off (--sparkplug-commands)"
        decision = granted(self.who, Act.of(command))
        if not decision.allowed:
            return command.value, "denied", decision.reason() + " (--sparkplug-role)"
        try:
            reply = self._channel.send_command(CommandRequest(next(self._ids), command),
                                               COMMAND_TIMEOUT_S)
        except (NotQueued, NoReply, ChannelFull) as exc:
            return command.value, "refused", str(exc)
        return command.value, ("applied" if reply.ok else "refused"), \
            ("" if reply.ok else reply.message)


def _plain(value: object) -> object:
    if isinstance(value, float) and value != value:
        return "NaN"
    if isinstance(value, float) and value in (float("inf"), float("-inf")):
        return "Infinity" if value > 0 else "-Infinity"
    return value
