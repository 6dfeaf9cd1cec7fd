"""The PLC as seen in the address space: values pushed from the snapshot and the status
board, and OPC UA events for what changed.

Owns: writing only changed values into the address space (subscribers are told of changes
only), rebuilding the program's nodes when the snapshot shows a new program hash and the
board describes it, the Part 10 state that follows the PLC state, and events for board
events, downloads, state changes, faults and refused commands; each value's quality (Good
while the scan process publishes, Uncertain_LastUsableValue once its snapshot is stale,
Bad_WaitingForInitialData before its first publish) and timestamps (Source: the publish of the
snapshot that carried the value, converted from CLOCK_MONOTONIC to wall-clock time; Server:
when it was written here).
Does not know: sessions, who may write, the channel, when to poll (server.py does).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Mapping
from datetime import UTC
from typing import Any, Final

from asyncua import Server, ua

from softplc.core.image import AddressError
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import Snapshot
from softplc.opcua.ids import status_code
from softplc.opcua.part10 import Part10, notifier_chain, trigger_everywhere
from softplc.opcua.program import Outcome
from softplc.opcua.space import PartState, Space, SymbolNode, part10_state

_STATUS_TYPES: Final = {"State": ua.VariantType.String, "ProgramHash": ua.VariantType.String,
                        "Program": ua.VariantType.String, "FaultReason": ua.VariantType.String,
                        "ScanCount": ua.VariantType.UInt64, "FaultCode": ua.VariantType.UInt16,
                        "WaitingForIo": ua.VariantType.Boolean, "Paused": ua.VariantType.Boolean,
                        "PauseReason": ua.VariantType.String}


class Mirror:
    """The address space of `space` kept in step with the PLC; `events` is asyncua's event
    generator of the SoftplcEventType."""

    def __init__(self, server: Server, space: Space, events: Any, modbus_writes: str) -> None:
        self._server = server
        self.space = space
        self._events = events
        self._modbus_writes = modbus_writes
        self.by_node: dict[ua.NodeId, SymbolNode] = {}
        self.built_hash: str | None = None  # the program whose nodes are built
        self._values: dict[Any, Any] = {}  # node id -> last (value, status) pushed
        self._fed: dict[ua.NodeId, ua.Variant] = {}  # the nodes fed by the scan process
        self._part10: PartState | None = None
        self.part10: Part10 | None = None  # LastTransition, Executable, transition events
        self._state: PlcState | None = None
        self._fault = 0
        self._event_seq = 0
        self._quality = ua.StatusCodes.BadWaitingForInitialData  # of the last snapshot pushed
        self._source: ua.DateTime | None = None  # its publish, wall-clock

    async def first_look(self, document: Mapping[str, Any], snapshot: Snapshot | None) -> None:
        """Nodes of the program that runs now; events from now on (no replay of old ones)."""
        self._event_seq = newest_seq(document)
        assert self.space.plc is not None and self.space.program is not None
        await notifier_chain(self._server, self.space.plc, self.space.program)
        transitions = await self._server.get_event_generator(
            ua.ObjectIds.ProgramTransitionEventType, self.space.program.nodeid)
        self.part10 = Part10(self._server, self.space.program, transitions,
                             above=(self.space.plc.nodeid,))  # PLC -HasNotifier-> Program
        if snapshot is not None:
            self._state = snapshot.status.state
            await self.maybe_rebuild(snapshot.status.program_hash, document)
            await self.push(snapshot)
        await self.follow(part10_state(snapshot.status.state, snapshot.status.marking_kept)
                          if snapshot is not None else PartState.HALTED)

    async def follow(self, state: PartState) -> bool:
        """The Program object in Part 10 `state`; False when it was in it already."""
        if state is self._part10:
            return False
        self._part10 = state
        await self.space.set_part10_state(state)
        if self.part10 is not None:
            await self.part10.set(state)
        return True

    async def maybe_rebuild(self, program_hash: str, document: Mapping[str, Any]) -> None:
        if (document.get("program_hash") or "") != program_hash:
            return  # the board does not describe this program yet: next board poll
        await self.space.build_program(document, self._modbus_writes)
        self.by_node = {s.node.nodeid: s for s in self.space.symbols.values()}
        self._values, self._fed = {}, {}
        previous, self.built_hash = self.built_hash, program_hash
        if previous is not None and program_hash:
            await self.emit("download", f"program {document.get('program')} loaded "
                            f"(sha256 {program_hash[:12]}), state {document.get('state')}")

    async def transitions(self, snapshot: Snapshot) -> None:
        status = snapshot.status
        part = part10_state(status.state, status.marking_kept)
        moved = await self.follow(part)
        if status.state is not self._state or moved:
            before, self._state = self._state, status.state
            await self.emit("state", f"{before.name if before else '?'} -> {status.state.name}"
                            f" (Part 10: {part.text})", scan=status.scan_count)
        if status.fault_code != self._fault:
            self._fault = status.fault_code
            if status.fault_code:
                await self.emit("fault", f"fault code {status.fault_code}",
                                scan=status.scan_count, severity=900)

    async def push(self, snapshot: Snapshot) -> None:
        image, status = snapshot.image, snapshot.status
        self._quality, self._source = quality(snapshot), source_time(snapshot)
        for symbol in self.by_node.values():
            if symbol.location is not None:
                with contextlib.suppress(AddressError, IndexError):
                    await self.set(symbol.node.nodeid, symbol.variant(image.get(symbol.location)),
                                   fed=True)
        nodes = self.space.status
        for name, value in (("State", status.state.name), ("ProgramHash", status.program_hash),
                            ("ScanCount", status.scan_count), ("PeriodUs", status.period_us),
                            ("LastExecUs", status.last_exec_us),
                            ("MaxExecUs", status.max_exec_us),
                            ("P99LatenessUs", status.p99_lateness_us),
                            ("Overruns", status.overruns), ("FaultCode", status.fault_code),
                            ("WaitingForIo", status.waiting_for_io)):
            await self.set(nodes[name].nodeid, _status_variant(name, value), fed=True)

    async def lost(self) -> None:
        """No snapshot can be read (the scan process died while publishing): every value it
        fed is the last usable one, Uncertain, until a snapshot is read again."""
        if self._quality == ua.StatusCodes.Good:
            self._quality = ua.StatusCodes.UncertainLastUsableValue
            for nodeid, variant in list(self._fed.items()):
                await self.set(nodeid, variant, fed=True)

    async def board_values(self, document: dict[str, Any]) -> None:
        if not document:
            return
        nodes = self.space.status
        await self.set(nodes["Program"].nodeid, _status_variant(
            "Program", document.get("program") or ""), fed=True)
        await self.set(nodes["FaultReason"].nodeid,
                       _status_variant("FaultReason", document.get("fault_reason") or ""),
                       fed=True)
        paused = document.get("paused")  # breakpoints (docs/debug.md): a sub-state of RUNNING
        reason = paused.get("reason") if isinstance(paused, dict) else ""
        await self.set(nodes["Paused"].nodeid, _status_variant("Paused", bool(paused)), fed=True)
        await self.set(nodes["PauseReason"].nodeid,
                       _status_variant("PauseReason", reason or ""), fed=True)
        restarts = document.get("restarts")
        if isinstance(restarts, int):
            await self.set(nodes["Restarts"].nodeid, _status_variant("Restarts", restarts),
                           fed=True)
        if document.get("program_hash") == self.built_hash:
            marking = document.get("marking") or {}
            for place in marking:
                await self.space.place(str(place))
            for place, node in self.space.places.items():  # unmarked places are absent: 0
                count = marking.get(place, 0)
                await self.set(node.nodeid, ua.Variant(count if isinstance(count, int) else 0,
                                                       ua.VariantType.UInt32), fed=True)
        await self._board_events(document)

    async def _board_events(self, document: dict[str, Any]) -> None:
        events = [e for e in document.get("events") or []
                  if isinstance(e, dict) and isinstance(e.get("seq"), int)]
        newest = newest_seq(document)
        if events and newest < self._event_seq:  # numbers start again: the supervisor lost
            self._event_seq = 0  # the dead scan process's (its board unreadable at the restart)
        for event in events:
            if event["seq"] > self._event_seq:
                name = str(event.get("name"))
                await self.emit(name, f"event {name}", seq=event["seq"],
                                scan=int(event.get("scan") or 0))
        self._event_seq = max(self._event_seq, newest)
        await self.set(self.space.status["LastEventSeq"].nodeid,
                       ua.Variant(self._event_seq & 0xFFFFFFFF, ua.VariantType.UInt32))

    async def command_done(self, method: str, outcome: Outcome) -> None:
        """A method call's result in LastResult/LastProblems; a refusal is also an event."""
        text = outcome.message if outcome.ok else f"{method} refused: {outcome.message}"
        await self.set(self.space.status["LastResult"].nodeid,
                       ua.Variant(text, ua.VariantType.String))
        await self.set(self.space.status["LastProblems"].nodeid,
                       ua.Variant(list(outcome.problems), ua.VariantType.String))
        if not outcome.ok:
            await self.emit("refused", text + "".join(f"\n{p}" for p in outcome.problems))
        elif outcome.state in PlcState.__members__:
            # The scan's reply says the state at once: the next call is checked against it
            # (program.py), not against a snapshot up to a poll older. CurrentState, events and
            # Status.State follow the snapshot together (a STOPPED reply of Suspend kept the
            # marking; of anything else, it holds the initial one).
            self.space.part10 = part10_state(PlcState[outcome.state], method == "Suspend")

    async def set(self, nodeid: ua.NodeId, variant: ua.Variant, *, fed: bool = False) -> None:
        """Write a value into the address space only when it or its quality changed
        (subscribers are told of changes only). `fed`: the value comes from the scan process
        (snapshot or board), so it carries the last snapshot's quality and publish time; else
        it is this process's own (Good, Source = now)."""
        status = self._quality if fed else ua.StatusCodes.Good
        key = (_same(variant.Value), status)
        if self._values.get(nodeid) == key:
            return
        self._values[nodeid] = key
        if fed:
            self._fed[nodeid] = variant
        now = ua.DateTime.now(UTC)
        source = self._source if fed and self._source is not None else now
        await self._server.write_attribute_value(nodeid, ua.DataValue(
            variant, StatusCode=status_code(status), SourceTimestamp=source, ServerTimestamp=now))

    async def emit(self, name: str, message: str, *, seq: int = 0, scan: int = 0,
                   severity: int = 500) -> None:
        event = self._events.event
        event.EventName, event.Seq, event.Scan = name, seq & 0xFFFFFFFF, scan
        event.Severity = severity
        await trigger_everywhere(self._events, message)


def _same(value: object) -> object:
    """What `value` is compared by: a float by its bits, so a NaN real equals itself (and is
    not written again, and notified, at every poll) and -0.0 differs from 0.0."""
    return value.hex() if isinstance(value, float) else value


def newest_seq(document: Mapping[str, Any]) -> int:
    return max((int(e["seq"]) for e in document.get("events") or []
                if isinstance(e, dict) and isinstance(e.get("seq"), int)), default=0)


def quality(snapshot: Snapshot) -> int:
    """Part 8's quality of the values of `snapshot`: Good while fresh; a stale one (the scan
    process stopped publishing: frozen, dead, restarting; runtime/shared/fresh.py) holds the last
    usable values, and one never published holds none."""
    if not snapshot.status.stale:
        return ua.StatusCodes.Good
    if not snapshot.status.published_ns:
        return ua.StatusCodes.BadWaitingForInitialData
    return ua.StatusCodes.UncertainLastUsableValue


def source_time(snapshot: Snapshot) -> ua.DateTime | None:
    """The publish of `snapshot` in wall-clock time: CLOCK_MONOTONIC (machine-wide) mapped by
    the offset between the two clocks now (a wall-clock step since the publish shifts it)."""
    published = snapshot.status.published_ns
    if not published:
        return None
    wall_ns = time.time_ns() - (time.monotonic_ns() - published)
    return ua.DateTime.fromtimestamp(wall_ns / 1e9, UTC)


def _status_variant(name: str, value: object) -> ua.Variant:
    vtype = _STATUS_TYPES.get(name, ua.VariantType.UInt32)
    if vtype is ua.VariantType.String:
        return ua.Variant(str(value), vtype)
    if vtype is ua.VariantType.Boolean:
        return ua.Variant(bool(value), vtype)
    return ua.Variant(int(value) if isinstance(value, int) else 0, vtype)
