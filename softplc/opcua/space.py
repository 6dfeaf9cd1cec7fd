"""The address space of one loaded program: which nodes exist and what they are called.

Owns: node ids (stable strings, so a client or another softplc can name them without
browsing), the symbols folder built from the board's symbol table (each symbol's DataType from
its type, typed.py; a scaled symbol an AnalogItemType with EngineeringUnits and EURange;
description, access level), the status variables, the marking folder, the Program object (an
instance of OPC UA Part 10's ProgramStateMachineType) and the mapping of PLC states onto its
states.
Does not know: sockets, sessions, the channel, when values change (server.py does).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from asyncua import Node, Server, ua

from softplc.core.image import Address, AddressError, parse_address
from softplc.core.lifecycle import PlcState, Stage, stage_of
from softplc.opcua.ids import numeric_id, string_id
from softplc.opcua.typed import UNKNOWN, Refusal, TypedSymbol, eu_information, eu_range
from softplc.security.writes import policy_refusal

NAMESPACE_URI: Final = "urn:softplc"
PLC: Final = "PLC"
SYMBOLS: Final = "PLC.Symbols"
STATUS: Final = "PLC.Status"
MARKING: Final = "PLC.Marking"
PROGRAM: Final = "PLC.Program"
METHODS: Final = ("Start", "Suspend", "Resume", "Halt", "Reset", "Download")


def symbol_id(name: str) -> str:
    return f"{SYMBOLS}.{name}"


def place_id(name: str) -> str:
    return f"{MARKING}.{name}"


class PartState(enum.Enum):
    """The states of ProgramStateMachineType (Part 10), with their StateNumber and node."""

    HALTED = ("Halted", 11, ua.ObjectIds.ProgramStateMachineType_Halted)
    READY = ("Ready", 12, ua.ObjectIds.ProgramStateMachineType_Ready)
    RUNNING = ("Running", 13, ua.ObjectIds.ProgramStateMachineType_Running)
    SUSPENDED = ("Suspended", 14, ua.ObjectIds.ProgramStateMachineType_Suspended)

    @property
    def text(self) -> str:
        return str(self.value[0])

    @property
    def node(self) -> ua.NodeId:
        return numeric_id(self.value[2])


def part10_state(state: PlcState, marking_kept: bool) -> PartState:
    """RUNNING is Running; STOPPED is Suspended when a stop kept its marking (Stage.SUSPENDED)
    and Ready when it holds the initial one (download, reset); EMPTY/KILLED/FAULTED are
    Halted (Part 10's idle state: cannot run, or ended)."""
    return _PART10[stage_of(state, marking_kept)]


_PART10: Final = {Stage.EMPTY: PartState.HALTED, Stage.KILLED: PartState.HALTED,
                  Stage.FAULTED: PartState.HALTED, Stage.READY: PartState.READY,
                  Stage.SUSPENDED: PartState.SUSPENDED, Stage.RUNNING: PartState.RUNNING}


@dataclass(frozen=True, slots=True)
class SymbolNode:
    name: str
    address: str
    typed: TypedSymbol
    writable: bool
    node: Node
    location: Address | None  # None: the board's address does not parse (never written)

    def variant(self, raw: int) -> ua.Variant:
        """The node's value for the raw bits of the symbol's location."""
        return self.typed.variant(raw)

    def written(self, variant: ua.Variant | None) -> int | Refusal:
        """The raw bits a client's write stores, or why it is refused."""
        return self.typed.written(self.name, variant)


# name -> (OPC UA type, initial value); fed from the snapshot's Status and the board.
STATUS_VARIABLES: Final[Mapping[str, tuple[ua.VariantType, Any]]] = {
    "State": (ua.VariantType.String, "EMPTY"),
    "Program": (ua.VariantType.String, ""),
    "ProgramHash": (ua.VariantType.String, ""),
    "ScanCount": (ua.VariantType.UInt64, 0),
    "PeriodUs": (ua.VariantType.UInt32, 0),
    "LastExecUs": (ua.VariantType.UInt32, 0),
    "MaxExecUs": (ua.VariantType.UInt32, 0),
    "P99LatenessUs": (ua.VariantType.UInt32, 0),
    "Overruns": (ua.VariantType.UInt32, 0),
    "FaultCode": (ua.VariantType.UInt16, 0),
    "FaultReason": (ua.VariantType.String, ""),
    "Restarts": (ua.VariantType.UInt32, 0),
    "LastEventSeq": (ua.VariantType.UInt32, 0),
    "WaitingForIo": (ua.VariantType.Boolean, False),  # docs/faults.md, start-up
    "Paused": (ua.VariantType.Boolean, False),  # docs/debug.md, breakpoints: still RUNNING
    "PauseReason": (ua.VariantType.String, ""),  # the breakpoint that hit, or a step's end
}


class Space:
    """The nodes of the server, built once (status, Program) and per program (symbols,
    marking). `build_program` replaces the per-program folders."""

    def __init__(self, server: Server, ns: int) -> None:
        self.server = server
        self.ns = ns
        self.plc: Node | None = None
        self.program: Node | None = None
        self.part10: PartState | None = None  # the Program object's CurrentState, once known
        self.status: dict[str, Node] = {}
        self.symbols: dict[str, SymbolNode] = {}
        self.places: dict[str, Node] = {}
        self._folders: list[Node] = []
        self._marking: Node | None = None

    def nid(self, text: str) -> ua.NodeId:
        return string_id(text, self.ns)

    async def build_static(self) -> None:
        objects = self.server.nodes.objects
        self.plc = await objects.add_object(self.nid(PLC), f"{self.ns}:{PLC}")
        status = await self.plc.add_folder(self.nid(STATUS), f"{self.ns}:Status")
        for name, (vtype, initial) in STATUS_VARIABLES.items():
            self.status[name] = await status.add_variable(
                self.nid(f"{STATUS}.{name}"), f"{self.ns}:{name}", ua.Variant(initial, vtype))
        self.program = await self.plc.add_object(
            self.nid(PROGRAM), f"{self.ns}:Program",
            objecttype=numeric_id(ua.ObjectIds.ProgramStateMachineType))
        for name, (vtype, initial) in {"LastResult": (ua.VariantType.String, ""),
                                       "LastProblems": (ua.VariantType.String, [])}.items():
            self.status[name] = await self.program.add_variable(
                self.nid(f"{PROGRAM}.{name}"), f"{self.ns}:{name}", ua.Variant(initial, vtype))
        await program_properties(self.server, self.program)

    async def set_part10_state(self, state: PartState) -> None:
        assert self.program is not None
        self.part10 = state
        current = await self.program.get_child("0:CurrentState")
        await current.write_value(ua.LocalizedText(state.text))
        state_id = await current.get_child("0:Id")
        await state_id.write_value(ua.Variant(state.node, ua.VariantType.NodeId))
        number = await _optional_child(current, "0:Number")
        if number is not None:
            await number.write_value(ua.Variant(state.value[1], ua.VariantType.UInt32))

    async def build_program(self, document: Mapping[str, Any], policy: str) -> None:
        """Symbols and marking of the board's program; the previous ones are deleted."""
        assert self.plc is not None
        if self._folders:
            await self.server.delete_nodes(self._folders, recursive=True)
        self.symbols, self.places = {}, {}
        symbols = await self.plc.add_folder(self.nid(SYMBOLS), f"{self.ns}:Symbols")
        marking = await self.plc.add_folder(self.nid(MARKING), f"{self.ns}:Marking")
        self._folders = [symbols, marking]
        self._marking = marking
        table = document.get("symbols") or {}
        for name, entry in table.items():
            if isinstance(entry, dict):
                self.symbols[name] = await self._symbol(symbols, str(name), entry, policy)
        for place in document.get("places") or document.get("marking") or {}:
            await self.place(str(place))

    async def place(self, name: str) -> Node:
        """The marking variable of `name`, added when first seen: the board lists marked
        places only (and every place when it has a "places" key)."""
        node = self.places.get(name)
        if node is None:
            assert self._marking is not None
            node = await self._marking.add_variable(
                self.nid(place_id(name)), f"{self.ns}:{name}", ua.Variant(0, ua.VariantType.UInt32))
            self.places[name] = node
        return node

    async def _symbol(self, folder: Node, name: str, entry: Mapping[str, Any],
                      policy: str) -> SymbolNode:
        typed = TypedSymbol.of(entry)
        writable = policy_refusal(name, entry, policy) is None and typed.vtype is not UNKNOWN
        raw = entry.get("raw")
        variant = typed.variant(raw if isinstance(raw, int) else 0)  # the snapshot's next
        node = await _variable(folder, self.nid(symbol_id(name)), f"{self.ns}:{name}",
                               variant, analog=typed.scale is not None)
        if typed.scale is not None:
            await _analog_properties(node, typed)
        text = f"{entry.get('address')} ({entry.get('direction')})"
        description = str(entry.get("description") or "")
        await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(
            ua.Variant(ua.LocalizedText(f"{description} [{text}]".strip()),
                       ua.VariantType.LocalizedText)))
        if writable:
            await node.set_writable(True)
        try:
            location: Address | None = parse_address(str(entry.get("address")))
        except AddressError:
            location = None
        return SymbolNode(name, str(entry.get("address")), typed, writable, node, location)


async def _variable(folder: Node, nodeid: ua.NodeId, name: str, variant: ua.Variant, *,
                    analog: bool) -> Node:
    """A symbol's variable: DataType the variant's (Int16 for an int, not the BaseDataType
    a guess would give a Variant), type definition Part 8's AnalogItemType for a scaled
    symbol (asyncua has no helper: its add_variable always makes a BaseDataVariableType)."""
    if not analog:
        return await folder.add_variable(nodeid, name, variant,
                                         datatype=numeric_id(variant.VariantType.value))
    qname = ua.QualifiedName.from_string(name)
    attrs = ua.VariableAttributes(
        DisplayName=ua.LocalizedText(qname.Name), Description=ua.LocalizedText(qname.Name),
        DataType=numeric_id(variant.VariantType.value), Value=variant,
        ValueRank=ua.ValueRank.Scalar, WriteMask=0, UserWriteMask=0,
        Historizing=False, AccessLevel=ua.AccessLevel.CurrentRead.mask,
        UserAccessLevel=ua.AccessLevel.CurrentRead.mask)
    item = ua.AddNodesItem(
        ParentNodeId=folder.nodeid, ReferenceTypeId=numeric_id(ua.ObjectIds.HasComponent),
        RequestedNewNodeId=nodeid, BrowseName=qname, NodeClass=ua.NodeClass.Variable,
        NodeAttributes=attrs, TypeDefinition=numeric_id(ua.ObjectIds.AnalogItemType))
    result = (await folder.session.add_nodes([item]))[0]
    result.StatusCode.check()
    return Node(folder.session, result.AddedNodeId)


async def _analog_properties(node: Node, typed: TypedSymbol) -> None:
    """Part 8's EURange (mandatory) and EngineeringUnits (when the scale names a unit)."""
    assert typed.scale is not None
    base = f"{node.nodeid.Identifier!s}"
    await node.add_property(
        string_id(f"{base}.EURange", node.nodeid.NamespaceIndex), "0:EURange",
        ua.Variant(eu_range(typed.scale), ua.VariantType.ExtensionObject),
        datatype=numeric_id(ua.ObjectIds.Range))
    if typed.scale.unit:
        await node.add_property(
            string_id(f"{base}.EngineeringUnits", node.nodeid.NamespaceIndex),
            "0:EngineeringUnits",
            ua.Variant(eu_information(typed.scale.unit), ua.VariantType.ExtensionObject),
            datatype=numeric_id(ua.ObjectIds.EUInformation))


async def _optional_child(node: Node, path: str) -> Node | None:
    try:
        return await node.get_child(path)
    except ua.UaStatusCodeError:
        return None


async def program_properties(server: Server, program: Node) -> None:
    """What asyncua leaves null on the instance: the optional properties get their values
    (one program, neither deletable nor recycled), the optional ProgramDiagnostic goes (absent
    rather than null), the methods get their OutputArguments (Message, State)."""
    values = {"0:Deletable": ua.Variant(False, ua.VariantType.Boolean),
              "0:AutoDelete": ua.Variant(False, ua.VariantType.Boolean),
              "0:RecycleCount": ua.Variant(0, ua.VariantType.Int32),
              "0:AvailableStates": ua.Variant([s.node for s in PartState],
                                              ua.VariantType.NodeId),
              "0:AvailableTransitions": ua.Variant(
                  [numeric_id(getattr(ua.ObjectIds, f"ProgramStateMachineType_{t}"))
                   for t in TRANSITION_NAMES], ua.VariantType.NodeId)}
    for path, variant in values.items():
        node = await _optional_child(program, path)
        if node is not None:
            await node.write_value(variant)
    diagnostic = await _optional_child(program, "0:ProgramDiagnostic")
    if diagnostic is not None:
        await server.delete_nodes([diagnostic], recursive=True)
    outputs = [ua.Argument(Name=name, DataType=numeric_id(ua.ObjectIds.String), ValueRank=-1,
                           Description=ua.LocalizedText(text)) for name, text in OUTPUTS]
    for method in METHODS[:5]:
        node = await program.get_child(f"0:{method}")
        if await _optional_child(node, "0:OutputArguments") is None:
            prop = await node.add_property(
                string_id(f"{node.nodeid.Identifier!s}.OutputArguments",
                          node.nodeid.NamespaceIndex),
                "0:OutputArguments", ua.Variant(outputs, ua.VariantType.ExtensionObject),
                datatype=numeric_id(ua.ObjectIds.Argument))
            await prop.write_value_rank(1)


TRANSITION_NAMES: Final = ("HaltedToReady", "ReadyToRunning", "RunningToHalted",
                           "RunningToReady", "RunningToSuspended", "SuspendedToRunning",
                           "SuspendedToHalted", "SuspendedToReady", "ReadyToHalted")
OUTPUTS: Final = (("Message", "what the PLC did or why it refused"),
                  ("State", "PLC state after the command"))
