"""OPC UA Part 10 (Programs) on the Program object: the state machine as the spec has it.

Owns: which methods each state accepts (Executable
and UserExecutable of the method nodes, and the check before a call is sent), the standard
transitions (LastTransition with Id, Number and TransitionTime), ProgramTransitionEventType
events, and raising events on their source and on every notifier above it up to the Server
object (i=2253, where generic clients subscribe): Program -> PLC -> Server (asyncua delivers
an event only to the node it is triggered on).
Does not know: the channel, sessions, the scan, when the PLC changes (mirror.py says).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Final

from asyncua import Node, Server, ua

from softplc.opcua.ids import numeric_id
from softplc.opcua.space import PartState

P = PartState
# Part 10's table: the states each method leaves. Reset is only HaltedToReady (a Suspended
# program is halted first); Halt leaves every state but Halted. Download is softplc's own.
ACCEPTED_IN: Final[dict[str, frozenset[PartState]]] = {
    "Start": frozenset({P.READY}), "Suspend": frozenset({P.RUNNING}),
    "Resume": frozenset({P.SUSPENDED}), "Halt": frozenset({P.READY, P.RUNNING, P.SUSPENDED}),
    "Reset": frozenset({P.HALTED})}
TYPE_METHODS: Final = {ua.ObjectIds.ProgramStateMachineType_Start: "Start",
                       ua.ObjectIds.ProgramStateMachineType_Suspend: "Suspend",
                       ua.ObjectIds.ProgramStateMachineType_Resume: "Resume",
                       ua.ObjectIds.ProgramStateMachineType_Halt: "Halt",
                       ua.ObjectIds.ProgramStateMachineType_Reset: "Reset"}
_T = ua.ObjectIds
# (from, to) -> (name, node of the type's transition, TransitionNumber)
TRANSITIONS: Final[dict[tuple[PartState, PartState], tuple[str, int, int]]] = {
    (P.HALTED, P.READY): ("HaltedToReady", _T.ProgramStateMachineType_HaltedToReady, 1),
    (P.READY, P.RUNNING): ("ReadyToRunning", _T.ProgramStateMachineType_ReadyToRunning, 2),
    (P.RUNNING, P.HALTED): ("RunningToHalted", _T.ProgramStateMachineType_RunningToHalted, 3),
    (P.RUNNING, P.READY): ("RunningToReady", _T.ProgramStateMachineType_RunningToReady, 4),
    (P.RUNNING, P.SUSPENDED): ("RunningToSuspended",
                               _T.ProgramStateMachineType_RunningToSuspended, 5),
    (P.SUSPENDED, P.RUNNING): ("SuspendedToRunning",
                               _T.ProgramStateMachineType_SuspendedToRunning, 6),
    (P.SUSPENDED, P.HALTED): ("SuspendedToHalted",
                              _T.ProgramStateMachineType_SuspendedToHalted, 7),
    (P.SUSPENDED, P.READY): ("SuspendedToReady", _T.ProgramStateMachineType_SuspendedToReady, 8),
    (P.READY, P.HALTED): ("ReadyToHalted", _T.ProgramStateMachineType_ReadyToHalted, 9),
}
_WHAT_WORKS: Final = {
    ("Start", P.SUSPENDED): "Resume continues from the kept marking; Halt then Reset then "
                            "Start runs from the initial marking",
    ("Reset", P.SUSPENDED): "Part 10 resets a Halted program only: Halt first (or Resume)",
    ("Reset", P.READY): "the program is Ready already: Start runs it",
    ("Resume", P.READY): "nothing to resume: Start runs the initial marking",
}


def refusal(method: str, state: PartState) -> str | None:
    """Why `method` may not run in `state` by Part 10 (None: it may)."""
    accepted = ACCEPTED_IN.get(method)
    if accepted is None or state in accepted:
        return None
    names = ", ".join(sorted(s.text for s in accepted))
    hint = _WHAT_WORKS.get((method, state))
    return (f"{method} is not accepted in Part 10 state {state.text} (accepted in {names})"
            + (f": {hint}" if hint else ""))


class Part10:
    """The Program object's Part 10 behaviour; `set` is told every state the PLC is in."""

    def __init__(self, server: Server, program: Node, transition_events: Any,
                 above: tuple[ua.NodeId, ...] = ()) -> None:
        self._server = server
        self._program = program
        self._events = transition_events
        self._above = above  # the notifiers between the Program and the Server object
        self.state: PartState | None = None

    async def set(self, state: PartState) -> None:
        """Follow the PLC into `state`: LastTransition and an event when Part 10 has the
        transition (a device recovery, FAULTED -> RUNNING, has none: CurrentState only)."""
        before, self.state = self.state, state
        if before is state:
            return
        await self._executable(state)
        transition = TRANSITIONS.get((before, state)) if before is not None else None
        if transition is None or before is None:
            return
        now = datetime.now(UTC)
        await self._last_transition(transition, now)
        await self._event(before, state, transition, now)

    async def _executable(self, state: PartState) -> None:
        for method, accepted in ACCEPTED_IN.items():
            node = await self._program.get_child(f"0:{method}")
            value = ua.DataValue(ua.Variant(state in accepted, ua.VariantType.Boolean))
            await node.write_attribute(ua.AttributeIds.Executable, value)
            await node.write_attribute(ua.AttributeIds.UserExecutable, value)

    async def _last_transition(self, transition: tuple[str, int, int], now: datetime) -> None:
        name, node, number = transition
        last = await self._program.get_child("0:LastTransition")
        await last.write_value(ua.LocalizedText(name))
        for child, variant in (("0:Id", ua.Variant(numeric_id(node), ua.VariantType.NodeId)),
                               ("0:Number", ua.Variant(number, ua.VariantType.UInt32)),
                               ("0:TransitionTime", ua.Variant(now, ua.VariantType.DateTime))):
            await (await last.get_child(child)).write_value(variant)

    async def _event(self, before: PartState, state: PartState,
                     transition: tuple[str, int, int], now: datetime) -> None:
        event = self._events.event
        event.Transition = ua.LocalizedText(transition[0])
        # these properties are BaseDataType: their value goes as a Variant of its own
        setattr(event, "Transition/Id", _node_variant(numeric_id(transition[1])))
        event.FromState, event.ToState = ua.LocalizedText(before.text), ua.LocalizedText(state.text)
        setattr(event, "FromState/Id", _node_variant(before.node))
        setattr(event, "ToState/Id", _node_variant(state.node))
        event.Severity = 500
        await trigger_everywhere(self._events, f"{transition[0]}: {before.text} -> {state.text}",
                                 now, self._above)


def _node_variant(node: ua.NodeId) -> ua.Variant:
    return ua.Variant(node, ua.VariantType.NodeId)


async def trigger_everywhere(generator: Any, message: str, when: datetime | None = None,
                             above: tuple[ua.NodeId, ...] = ()) -> None:
    """Trigger the event of `generator` on its source, then the same event (same EventId,
    SourceNode still the source) on each notifier `above` it and on the Server object, the
    top of every softplc node's notifier chain (HasNotifier, Part 3): a subscription on any
    node of the chain receives what happens below it."""
    await generator.trigger(time_attr=when, message=message)
    event = generator.event
    source = event.emitting_node
    try:
        for notifier in (*above, numeric_id(ua.ObjectIds.Server)):
            event.emitting_node = notifier
            await generator.isession.subscription_service.trigger_event(event)
    finally:
        event.emitting_node = source


async def notifier_chain(server: Server, plc: Node, program: Node) -> None:
    """Server -HasNotifier-> PLC -HasNotifier-> Program, EventNotifier set on both: Part 3's
    way for a client to find the sources of what a subscription on Server receives."""
    await server.nodes.server.add_reference(plc.nodeid, ua.ObjectIds.HasNotifier)
    await plc.add_reference(program.nodeid, ua.ObjectIds.HasNotifier)
    for node in (plc, program):
        await node.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
