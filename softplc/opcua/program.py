"""Program handling as OPC UA methods: Start, Suspend, Resume, Halt, Reset (Part 10's
ProgramStateMachineType) and Download, sent to the scan process as the HTTP API sends them.

Owns: the method table (Part 10 name -> softplc Command), input/output arguments, checking
Download's arguments, asking the program gate (security/programgate.py: the signature and
its version, AllowOlder, as for HTTP) before a download is sent and telling it what the PLC
took, sending the command over the channel off the event loop, and mapping a refusal onto an
OPC UA status code with its reason (Bad status + the reason as output); Part 4's answer to a
call that names no object or no method (`misnamed`: asyncua's is BadNodeIdInvalid for both).
Does not know: sessions and who may call (server.py guards that), the address space layout.
"""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import re
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, Final, Protocol

from asyncua import ua

from softplc.core.lifecycle import Command
from softplc.core.snapshot import (
    DOWNLOAD_REFUSED,
    ChannelFull,
    CommandReply,
    CommandRequest,
    HmiWrite,
)
from softplc.opcua.ids import numeric_id, status_code, string_id
from softplc.opcua.part10 import TYPE_METHODS, refusal
from softplc.opcua.space import METHODS, PROGRAM, Space
from softplc.security.programgate import ProgramGate, ProgramRefused

COMMAND_TIMEOUT_S: Final = 8.0  # as the HTTP API: below a client's usual 10 s
DOWNLOAD_TIMEOUT_S: Final = 60.0  # a download compiles off the scan; a big net takes seconds
MAX_PROGRAM_BYTES: Final = 1 << 20  # as the API's body limit
_NAME: Final = re.compile(r"[A-Za-z0-9._-]{1,128}")
# OPC UA method name -> softplc command (Part 10: Suspend = stop, Halt = kill).
COMMANDS: Final = {"Start": Command.START, "Suspend": Command.STOP, "Resume": Command.RESUME,
                   "Halt": Command.KILL, "Reset": Command.RESET, "Download": Command.DOWNLOAD}
_FIRST_ID: Final = 1_000_000  # the API counts from 1; these ids show OPC UA in the trace


class CommandChannel(Protocol):
    """What the server needs of softplc.runtime.shared.channel.Channel (client side)."""

    def send_command(self, request: CommandRequest, timeout_s: float = ...) -> CommandReply: ...

    def send_hmi_write(self, write: HmiWrite) -> None: ...


@dataclass(frozen=True, slots=True)
class Outcome:
    """What one method call came to: `status` Good or the refusal's code."""

    status: int  # a ua.StatusCodes constant (plain ints)
    message: str
    state: str = ""
    problems: tuple[str, ...] = ()

    @property
    def ok(self) -> bool:
        return self.status == ua.StatusCodes.Good

    def result(self) -> ua.CallMethodResult:
        """Output arguments (Message, State[, Problems]) go with a Bad status too: a Bad
        method result alone carries no text, and clients that read the raw result get it."""
        outputs = [ua.Variant(self.message, ua.VariantType.String),
                   ua.Variant(self.state, ua.VariantType.String)]
        return ua.CallMethodResult(StatusCode=status_code(self.status),
                                   OutputArguments=outputs)


def arguments(method: str) -> tuple[list[ua.Argument], list[ua.Argument]]:
    """Input and output arguments of one method, as Part 3 Argument structures."""
    outputs = [_arg("Message", ua.VariantType.String, "what the PLC did or why it refused"),
               _arg("State", ua.VariantType.String, "PLC state after the command")]
    if method != "Download":
        return [], outputs
    return [_arg("ProgramText", ua.VariantType.String, "the program, YAML text"),
            _arg("Online", ua.VariantType.Boolean, "swap while RUNNING (online change)"),
            _arg("Name", ua.VariantType.String, "file name for messages ('' = downloaded.yaml)"),
            _arg("Signature", ua.VariantType.String, "the signature line of the text's UTF-8 "
                 "bytes (softplc sign; '' = unsigned): needed when the PLC trusts keys"),
            _arg("AllowOlder", ua.VariantType.Boolean, "take a signed version older than "
                 "the running one (a rollback; default false)"),
            ], outputs


def _arg(name: str, vtype: ua.VariantType, text: str) -> ua.Argument:
    return ua.Argument(Name=name, DataType=numeric_id(vtype.value), ValueRank=-1,
                       Description=ua.LocalizedText(text))


class ProgramHandling:
    """Sends program commands for the server; `on_outcome` hears every outcome. A download
    goes through `gate` (security/programgate.py) before anything parses it."""

    def __init__(self, channel: CommandChannel,
                 on_outcome: Callable[[str, Outcome], Awaitable[None]],
                 gate: ProgramGate) -> None:
        self._channel = channel
        self._gate = gate
        self._on_outcome = on_outcome
        self._ids = itertools.count(_FIRST_ID)
        self.space: Space | None = None  # the address space, once the server built it

    def method_of(self, request: ua.CallMethodRequest) -> str | None:
        """The program method a call names, by the instance's method id or the type's
        (Part 4: a type's method id called on an instance reaches the instance); None: not
        ours (asyncua answers it)."""
        method_id = request.MethodId
        if method_id.NamespaceIndex == 0 and method_id.Identifier in TYPE_METHODS:
            return TYPE_METHODS[int(method_id.Identifier)]
        if self.space is None:
            return None
        for name in METHODS:
            if method_id == string_id(f"{PROGRAM}.{name}", self.space.ns):
                return name
        return None

    async def call(self, method: str, args: list[ua.Variant],
                   object_id: ua.NodeId | None = None) -> ua.CallMethodResult:
        outcome = self._misdirected(method, object_id) or \
            await self._outcome(method, [a.Value for a in args])
        await self._on_outcome(method, outcome)
        return outcome.result()

    def _misdirected(self, method: str, object_id: ua.NodeId | None) -> Outcome | None:
        """A call on another object than the Program (Part 4: BadMethodInvalid), or one that
        Part 10's state machine does not allow in the Program's state (BadInvalidState)."""
        space = self.space
        if space is None or space.program is None:
            return None
        if object_id is not None and object_id != space.program.nodeid:
            return Outcome(ua.StatusCodes.BadMethodInvalid,
                           f"{method} is a method of {PROGRAM}, not of {object_id.to_string()}")
        reason = refusal(method, space.part10) if space.part10 is not None else None
        return None if reason is None else Outcome(ua.StatusCodes.BadInvalidState, reason)

    async def _outcome(self, method: str, values: list[object]) -> Outcome:
        command = COMMANDS[method]
        if command is not Command.DOWNLOAD:
            if values:
                return Outcome(ua.StatusCodes.BadTooManyArguments,
                               f"{method} takes no arguments, got {len(values)}")
            return await self._send(CommandRequest(next(self._ids), command))
        checked = _download_args(values)
        if isinstance(checked, Outcome):
            return checked
        try:  # one signed download at a time at every door: its version checked and advanced
            async with self._gate.turn(checked[3]):
                return await self._download(*checked)
        except ProgramRefused as exc:
            return Outcome(ua.StatusCodes.BadSecurityChecksFailed, exc.reason,
                           problems=(exc.reason,))

    async def _download(self, text: str, online: bool, name: str | None, signature: str | None,
                        allow_older: bool) -> Outcome:
        body = text.encode("utf-8")
        # the exact bytes, before anything parses them: as the HTTP door (ProgramRefused)
        signer = await asyncio.to_thread(self._gate.admit, body, signature, allow_older)
        if signer is not None:
            await asyncio.to_thread(self._gate.remember, body, signer)
        outcome = await self._send(CommandRequest(next(self._ids), Command.DOWNLOAD,
                                                  program_text=text, program_path=name,
                                                  online=online))
        if signer is None or signature is None or not outcome.ok:
            return outcome
        # The version now runs; the message (and so the audit record) says it, and a rollback.
        note = await asyncio.to_thread(self._gate.applied, body, signature, signer,
                                       allow_older)
        return dataclasses.replace(outcome,
                                   message=f"{outcome.message} (signed by {signer}{note})")

    async def _send(self, request: CommandRequest) -> Outcome:
        timeout_s = DOWNLOAD_TIMEOUT_S if request.command is Command.DOWNLOAD else \
            COMMAND_TIMEOUT_S
        # Past its deadline the scan refuses the command: a caller that gave up never sees
        # it happen later (CommandRequest.deadline_ns, CLOCK_MONOTONIC).
        request = dataclasses.replace(request, deadline_ns=time.clock_gettime_ns(
            time.CLOCK_MONOTONIC) + int(timeout_s * 1e9))
        try:
            reply = await asyncio.to_thread(self._channel.send_command, request, timeout_s)
        except TimeoutError as exc:
            return Outcome(ua.StatusCodes.BadTimeout, str(exc))
        except ChannelFull as exc:  # the scan process is not draining its commands
            return Outcome(ua.StatusCodes.BadResourceUnavailable, str(exc))
        return _reply_outcome(reply)


def misnamed(request: ua.CallMethodRequest, aspace: Any) -> ua.CallMethodResult | None:
    """Part 4's answer to a call whose ObjectId names no node (BadNodeIdUnknown, as a Write
    to it) or whose MethodId names no Method (BadMethodInvalid); None: asyncua may run it.
    `aspace`: asyncua's address space (`in`, and `[id].attributes`)."""
    if request.ObjectId not in aspace:
        return Outcome(ua.StatusCodes.BadNodeIdUnknown,
                       f"no object {request.ObjectId.to_string()}").result()
    method_id = request.MethodId
    node_class = aspace[method_id].attributes[ua.AttributeIds.NodeClass].value.Value.Value \
        if method_id in aspace else None
    if node_class != ua.NodeClass.Method:
        return Outcome(ua.StatusCodes.BadMethodInvalid,
                       f"{method_id.to_string()} is not a method").result()
    return None


def _download_args(values: list[object]
                   ) -> tuple[str, bool, str | None, str | None, bool] | Outcome:
    if len(values) < 2:
        return Outcome(ua.StatusCodes.BadArgumentsMissing,
                       "Download needs ProgramText (String) and Online (Boolean)")
    if len(values) > 5:
        return Outcome(ua.StatusCodes.BadTooManyArguments, "Download takes ProgramText, "
                       "Online, and an optional Name, Signature and AllowOlder")
    defaults: list[object] = ["", "", False]  # Name, Signature, AllowOlder
    text, online, name, signature, allow_older = [*values, *defaults[len(values) - 2:]]
    if not isinstance(text, str) or not isinstance(online, bool) or not isinstance(name, str) \
            or not isinstance(signature, str) or not isinstance(allow_older, bool):
        return Outcome(ua.StatusCodes.BadTypeMismatch, "Download arguments: ProgramText "
                       "String, Online Boolean, Name String, Signature String, AllowOlder "
                       "Boolean")
    if len(text.encode()) > MAX_PROGRAM_BYTES:
        return Outcome(ua.StatusCodes.BadEncodingLimitsExceeded,
                       f"the program is larger than {MAX_PROGRAM_BYTES} bytes")
    if name and not _NAME.fullmatch(name):
        return Outcome(ua.StatusCodes.BadInvalidArgument,
                       "Name must be a plain file name (letters, digits, . _ -)")
    if not text.strip():
        return Outcome(ua.StatusCodes.BadInvalidArgument, f"{DOWNLOAD_REFUSED}: empty program",
                       problems=(f"{name or 'program'}:1: the request holds no program",))
    return text, online, name or None, signature or None, allow_older


def _reply_outcome(reply: CommandReply) -> Outcome:
    state = reply.state.name
    if reply.ok:
        return Outcome(ua.StatusCodes.Good, reply.message, state)
    if reply.refusal is not None and reply.refusal.of_program:
        head = reply.message.partition("\n")[0]
        return Outcome(ua.StatusCodes.BadInvalidArgument, head.rstrip(":"), state,
                       reply.problems or (head,))
    # The lifecycle table refused the command in this state (or the scan did, e.g. an
    # online change it cannot make): the program is in the wrong state for it.
    return Outcome(ua.StatusCodes.BadInvalidState, reply.message, state)
