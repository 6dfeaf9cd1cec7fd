"""Wire contracts: the numbers and names that clients outside softplc read, pinned in one place.

An HMI reads the PLC state as register 1024, a SCADA client reads Part 10's StateNumber, a
script branches on the HTTP status of a refused download. None of them sees our enums, so a
renumbering, a renamed command or a moved register breaks them silently: here it breaks a
test, and its message says who reads the value. The expected values are written out, never
read from the constants they check (issue 43). In process: no socket, no process, no sleep.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from aiohttp import web
from aiohttp.test_utils import make_mocked_request
from asyncua import ua

from softplc.api import programs
from softplc.api.accessroutes import admit
from softplc.api.problems import ApiProblem
from softplc.api.server import ApiServer
from softplc.api.signed import DownloadSigning
from softplc.core.image import ImageSizes, ProcessImage
from softplc.core.lifecycle import Command, PlcState
from softplc.core.problems import FaultCode
from softplc.core.snapshot import (
    ChannelFull,
    CommandReply,
    CommandRequest,
    HmiWrite,
    Refusal,
    Snapshot,
    Status,
)
from softplc.hmi import map as hmi_map
from softplc.hmi.map import ExceptionCode, RegisterMap, Table
from softplc.opcua import space
from softplc.opcua.part10 import TRANSITIONS
from softplc.opcua.space import PartState, part10_state
from softplc.security.roles import Role


def contract(what: str, who: str) -> str:
    return (f"wire contract broken: {what}. {who} read this value over the wire: never "
            "renumber or rename it, only append (issue 43)")


HMI = "HMIs and SCADA (Modbus status block, OPC UA)"

# -- PLC states and fault codes ---------------------------------------------------------------


def test_contract_plc_state_numbers_and_names() -> None:
    """Register 1024 holds the number, OPC UA's PLC.Status.State and the API the name."""
    assert {s.name: int(s) for s in PlcState} == {
        "EMPTY": 0, "STOPPED": 1, "RUNNING": 2, "KILLED": 3, "FAULTED": 4}, \
        contract("PlcState numbers (register 1024, docs/modbus.md)", HMI)


def test_contract_fault_code_numbers() -> None:
    assert {f.name: int(f) for f in FaultCode} == {
        "NONE": 0, "WATCHDOG": 1, "DEVICE": 2, "PROGRAM": 3, "LIMIT": 4, "STALL": 5,
        "INTERNAL": 6}, contract("FaultCode numbers (register 1025, PLC.Status.FaultCode)", HMI)


# -- command wire names -----------------------------------------------------------------------


def test_contract_command_wire_names() -> None:
    """The names the CLI, the API (`POST /api/v1/<name>`), the channel and the audit trail use."""
    assert {c.name: c.value for c in Command} == {
        "DOWNLOAD": "download", "START": "start", "STOP": "stop", "RESUME": "resume",
        "RESET": "reset", "KILL": "kill", "FORCE": "force", "UNFORCE": "unforce",
        "BREAK": "break", "UNBREAK": "unbreak", "STEP": "step", "CONTINUE": "continue"}, \
        contract("command wire names", "the CLI, scripts of the HTTP API and audit readers")


# -- the Modbus status block and exception codes ----------------------------------------------


STATUS = Status(state=PlcState.FAULTED, scan_count=0x12345678, last_exec_us=70_000,
                max_exec_us=5, p99_lateness_us=6, overruns=7, program_hash="0123456789abcdef99",
                fault_code=2, period_us=10_000, forced=3, waiting_for_io=True, stale=True)
# Register by register, what `STATUS` reads as (docs/modbus.md, "Status block").
STATUS_WORDS = [4, 2, 0x1234, 0x5678, 1, 70_000 - 65_536, 0, 5, 0, 6, 0, 7, 0, 10_000,
                0x0123, 0x4567, 0x89AB, 0xCDEF, 3, 0b11]


def test_contract_modbus_status_block_layout() -> None:
    offsets = {name: getattr(hmi_map, name) for name in dir(hmi_map)
               if name.startswith("STATUS_") and name != "STATUS_WORDS"}
    assert offsets == {
        "STATUS_STATE": 0, "STATUS_FAULT_CODE": 1, "STATUS_SCAN_COUNT": 2,
        "STATUS_LAST_EXEC_US": 4, "STATUS_MAX_EXEC_US": 6, "STATUS_P99_LATENESS_US": 8,
        "STATUS_OVERRUNS": 10, "STATUS_PERIOD_US": 12, "STATUS_PROGRAM_HASH": 14,
        "STATUS_FORCED": 18, "STATUS_FLAGS": 19}, contract("status block offsets", HMI)
    assert (hmi_map.STATUS_WORDS, hmi_map.FLAG_STALE, hmi_map.FLAG_WAITING_IO) == (20, 1, 2), \
        contract("status block size and flag bits", HMI)
    assert hmi_map.status_registers(STATUS) == STATUS_WORDS, \
        contract("status block register values (u32 high word first)", HMI)


def test_contract_modbus_status_block_is_input_registers_1024_to_1043() -> None:
    sizes = ImageSizes()
    snapshot = Snapshot(1, ProcessImage(sizes), STATUS)
    served = RegisterMap(sizes).read(snapshot, Table.INPUT_REGISTERS, 1024, 20)
    assert served == STATUS_WORDS, contract("status block at input register 1024", HMI)


def test_contract_modbus_exception_codes() -> None:
    assert {c.name: int(c) for c in ExceptionCode} == {
        "ILLEGAL_FUNCTION": 1, "ILLEGAL_DATA_ADDRESS": 2, "ILLEGAL_DATA_VALUE": 3,
        "SERVER_DEVICE_FAILURE": 4, "SERVER_DEVICE_BUSY": 6}, \
        contract("Modbus exception codes (Modbus Application Protocol V1.1b3, 7)", HMI)


# -- OPC UA node ids and Part 10 state numbers ------------------------------------------------


def test_contract_opcua_node_ids() -> None:
    ids = (space.NAMESPACE_URI, space.PLC, space.SYMBOLS, space.STATUS, space.MARKING,
           space.PROGRAM, space.symbol_id("fill_to"), space.place_id("belt.full"))
    assert ids == ("urn:softplc", "PLC", "PLC.Symbols", "PLC.Status", "PLC.Marking",
                   "PLC.Program", "PLC.Symbols.fill_to", "PLC.Marking.belt.full"), \
        contract("OPC UA namespace and string node ids (docs/opcua.md)", "OPC UA clients")
    assert space.METHODS == ("Start", "Suspend", "Resume", "Halt", "Reset", "Download"), \
        contract("OPC UA method names of PLC.Program", "OPC UA clients")
    status = {name: variant for name, (variant, _) in space.STATUS_VARIABLES.items()}
    V = ua.VariantType
    assert status == {
        "State": V.String, "Program": V.String, "ProgramHash": V.String,
        "ScanCount": V.UInt64, "PeriodUs": V.UInt32, "LastExecUs": V.UInt32,
        "MaxExecUs": V.UInt32, "P99LatenessUs": V.UInt32, "Overruns": V.UInt32,
        "FaultCode": V.UInt16, "FaultReason": V.String, "Restarts": V.UInt32,
        "LastEventSeq": V.UInt32, "WaitingForIo": V.Boolean, "Paused": V.Boolean,
        "PauseReason": V.String}, contract("PLC.Status.* names and types", "OPC UA clients")


def test_contract_opcua_part10_state_numbers_and_nodes() -> None:
    """StateNumber and the state's node in namespace 0 (Part 10, ProgramStateMachineType)."""
    assert {s.value[0]: (s.value[1], s.value[2]) for s in PartState} == {
        "Halted": (11, 2406), "Ready": (12, 2400), "Running": (13, 2402),
        "Suspended": (14, 2404)}, contract("Part 10 StateNumber and state node ids",
                                          "OPC UA clients")
    assert {name: (number, node) for name, node, number in TRANSITIONS.values()} == {
        "HaltedToReady": (1, 2408), "ReadyToRunning": (2, 2410), "RunningToHalted": (3, 2412),
        "RunningToReady": (4, 2414), "RunningToSuspended": (5, 2416),
        "SuspendedToRunning": (6, 2418), "SuspendedToHalted": (7, 2420),
        "SuspendedToReady": (8, 2422), "ReadyToHalted": (9, 2424)}, \
        contract("Part 10 TransitionNumber and transition node ids", "OPC UA clients")
    shown = {(s.name, kept): part10_state(s, kept).value[0]
             for s in PlcState for kept in (False, True) if kept is False or s.name == "STOPPED"}
    assert shown == {("EMPTY", False): "Halted", ("STOPPED", False): "Ready",
                     ("STOPPED", True): "Suspended", ("RUNNING", False): "Running",
                     ("KILLED", False): "Halted", ("FAULTED", False): "Halted"}, \
        contract("PLC state -> Part 10 CurrentState", "OPC UA clients")


# -- the HTTP API's status codes per refusal kind ---------------------------------------------

SCRIPTS = "Scripts and clients of the HTTP API (docs/api.md)"


class _Channel:
    def __init__(self) -> None:
        self.full = False

    def send_command(self, request: CommandRequest, timeout_s: float = 0.0,
                     late: Any = None) -> CommandReply:
        if self.full:
            raise ChannelFull("the scan has not drained its queue")
        return CommandReply(request.id, True, "ok", PlcState.RUNNING)

    def send_hmi_write(self, write: HmiWrite) -> None:
        raise ChannelFull("the scan has not drained its queue")


class _Snapshots:
    def latest(self) -> Snapshot:
        return Snapshot(1, ProcessImage(ImageSizes()), Status(state=PlcState.RUNNING))


class _Board:
    def read(self) -> dict[str, Any]:
        return {}


@pytest.fixture
def api(tmp_path: Path) -> ApiServer:
    return ApiServer(_Channel(), _Snapshots(), _Board(), state_dir=tmp_path)


def _status(call: Any) -> tuple[int, Any]:
    try:
        call()
    except ApiProblem as problem:
        return problem.status, problem.extra.get("refusal")
    raise AssertionError("not refused")


def test_contract_http_status_of_each_refusal_kind(api: ApiServer) -> None:
    """422: the program itself is refused (resend a fixed one); 409: the moment or state is
    (a lifecycle refusal, a download withdrawn or expired: try again later or otherwise)."""
    routes = programs._Routes(api, api.signing)
    statuses = {}
    for kind in Refusal:
        reply = CommandReply(3, False, "download refused: because", PlcState.RUNNING,
                             refusal=kind, expired=kind is Refusal.EXPIRED)
        statuses[kind.value] = _status(lambda r=reply: routes._answer(r, None, None))
    program = {k: (422, k) for k in ("program", "analysis", "device", "compiler", "boot",
                                     "sizes", "signature")}
    assert statuses == {**program, "withdrawn": (409, None), "state": (409, None),
                        "expired": (409, None)}, contract("HTTP status per refusal kind", SCRIPTS)
    lifecycle = CommandReply(4, False, "start is not accepted in state RUNNING", PlcState.RUNNING,
                             refusal=Refusal.STATE)
    assert _status(lambda: api.answer(lifecycle)) == (409, None), \
        contract("409 for a command the lifecycle refuses", SCRIPTS)


def test_contract_http_422_for_an_unsigned_download(tmp_path: Path) -> None:
    signing = DownloadSigning(tmp_path, tmp_path / "trusted_keys", required=True)
    with pytest.raises(ApiProblem) as refused:
        asyncio.run(signing.check(b"places: {}\n", None))
    assert (refused.value.status, refused.value.extra) == (422, {"refusal": "signature"}), \
        contract("422 refusal 'signature' for an unsigned download", SCRIPTS)


def test_contract_http_503_when_the_command_was_not_sent(api: ApiServer) -> None:
    assert isinstance(api.channel, _Channel)
    api.channel.full = True
    with pytest.raises(ApiProblem) as refused:
        asyncio.run(api.command(Command.STOP))
    assert (refused.value.status, refused.value.headers) == (503, {"Retry-After": "1"}), \
        contract("503 with Retry-After when a command is not sent", SCRIPTS)


def _request(app: web.Application, method: str, path: str,
             headers: dict[str, str] | None = None) -> web.Request:
    async def resolved() -> web.Request:
        match = await app.router.resolve(make_mocked_request(method, path, app=app))
        return make_mocked_request(method, path, headers=headers, app=app, match_info=match)
    return asyncio.run(resolved())


def test_contract_http_401_403_429_at_the_gate(api: ApiServer) -> None:
    app = api.build_app()
    gate = api.gate
    anonymous = _request(app, "POST", "/api/v1/kill")
    with pytest.raises(ApiProblem) as no_credentials:
        asyncio.run(admit(gate, anonymous))
    gate.users.add("vera", Role.VIEWER, "a long enough password")
    key = gate.users.new_key("vera")
    viewer = _request(app, "POST", "/api/v1/kill", {"Authorization": f"Bearer {key}"})
    with pytest.raises(ApiProblem) as too_low:
        asyncio.run(admit(gate, viewer))
    backing_off = asyncio.run(gate.throttle(anonymous, "vera", 2.0))
    assert (no_credentials.value.status, too_low.value.status, backing_off.status) == \
        (401, 403, 429), contract("401 no credentials, 403 role too low, 429 backing off",
                                  SCRIPTS)
    assert "Retry-After" in backing_off.headers
