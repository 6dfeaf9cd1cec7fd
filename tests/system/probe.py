"""What the whole-system test sees of a run, and the three ways it sends commands.

Owns: one reading of the PLC (HTTP status, the Modbus status block, OPC UA's state, the
module's coils, the HMI memory), and sending a command over HTTP, OPC UA (asyncua calling the
program object's methods) or the CLI (`softplc stop` etc. as a process), each reduced to an
`Outcome` (applied, refused, expired, pending, none) with the time it took.
Does not know: what the PLC should say (the model does).
"""

from __future__ import annotations

import asyncio
import logging
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

from asyncua import ua
from pymodbus.client import ModbusTcpClient

from softplc.api.client import ApiError, ApiUnreachable
from softplc.hmi.map import (
    STATUS_FAULT_CODE,
    STATUS_FLAGS,
    STATUS_FORCED,
    STATUS_PROGRAM_HASH,
    STATUS_SCAN_COUNT,
    STATUS_STATE,
    STATUS_WORDS,
)
from tests.opcua.conftest import patient_client
from tests.system.programs import COILS, Module
from tests.system.rig import ROOT, Run

# asyncua warns at every session that its requested timeout was lowered: noise here
logging.getLogger("asyncua").setLevel(logging.ERROR)
# pymodbus logs an error with a dump of the last frames whenever a peer is gone: the module
# and the runs go away on purpose here
logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
STATUS_BASE = 1024  # input registers: %IW0..%IW1023, then the status block (docs/modbus.md)
STATE_CODES = {0: "EMPTY", 1: "STOPPED", 2: "RUNNING", 3: "KILLED", 4: "FAULTED"}
CMD_COIL, WORD_REGISTER = 800, 1024  # %MX0.0 (coils after %QX) and %MW0 (holding after %QW)
NS_URI = "urn:softplc"
DOWNLOAD_GIVE_UP_S = 25.0  # a 5-place program compiles in well under a second
OPCUA_METHODS = {"start": "0:Start", "stop": "0:Suspend", "resume": "0:Resume",
                 "reset": "0:Reset", "kill": "0:Halt"}


@dataclass(frozen=True)
class Outcome:
    """What one command ended as, as the client saw it."""

    kind: str  # applied | refused | expired | pending | none (no answer)
    state: str | None  # the state the reply named, if any
    seconds: float
    detail: str


@dataclass(frozen=True)
class Block:
    state: str
    fault_code: int
    scan_count: int
    hash64: int
    forced: int
    stale: bool


def block(run: Run) -> Block:
    client = ModbusTcpClient("127.0.0.1", port=run.modbus, timeout=3)
    try:
        reply = client.read_input_registers(STATUS_BASE, count=STATUS_WORDS, device_id=1)
        if reply.isError():
            raise AssertionError(f"status block read refused: {reply}")
        words = reply.registers
    finally:
        client.close()
    hash64 = 0
    for word in words[STATUS_PROGRAM_HASH:STATUS_PROGRAM_HASH + 4]:
        hash64 = hash64 << 16 | word
    return Block(STATE_CODES.get(words[STATUS_STATE], f"?{words[STATUS_STATE]}"),
                 words[STATUS_FAULT_CODE],
                 words[STATUS_SCAN_COUNT] << 16 | words[STATUS_SCAN_COUNT + 1], hash64,
                 words[STATUS_FORCED], bool(words[STATUS_FLAGS] & 1))


def memory(run: Run) -> tuple[bool, int]:
    """The HMI bit `cmd` and word `word` as the PLC's slave reads them."""
    client = ModbusTcpClient("127.0.0.1", port=run.modbus, timeout=3)
    try:
        bit = client.read_coils(CMD_COIL, count=1, device_id=1)
        word = client.read_holding_registers(WORD_REGISTER, count=1, device_id=1)
        assert not bit.isError() and not word.isError(), (bit, word)
        return bool(bit.bits[0]), int(word.registers[0])
    finally:
        client.close()


def hmi_write(run: Run, cmd: bool | None = None, word: int | None = None) -> None:
    client = ModbusTcpClient("127.0.0.1", port=run.modbus, timeout=3)
    try:
        if cmd is not None:
            reply = client.write_coil(CMD_COIL, cmd, device_id=1)
            assert not reply.isError(), f"HMI write of %MX0.0 refused: {reply}"
        if word is not None:
            reply = client.write_register(WORD_REGISTER, word, device_id=1)
            assert not reply.isError(), f"HMI write of %MW0 refused: {reply}"
    finally:
        client.close()


def coils(module: Module) -> list[bool]:
    return [bool(v) for v in module.get(1, 0, len(COILS))]


# -- OPC UA ---------------------------------------------------------------------------------

def opcua_state(run: Run) -> tuple[str, str]:
    """(PLC.Status.State, PLC.Program.CurrentState's text)."""
    async def read() -> tuple[str, str]:
        async with patient_client(run.opcua_url, 8) as client:
            ns = await client.get_namespace_index(NS_URI)
            state = await client.get_node(ua.NodeId("PLC.Status.State", ns)).read_value()
            current = await client.get_node(
                ua.NodeId("PLC.Program.CurrentState", ns)).read_value()
            return str(state), str(current.Text)
    return asyncio.run(asyncio.wait_for(read(), 20))


def _opcua_call(run: Run, method: str, *args: Any) -> Outcome:
    async def call() -> Outcome:
        client = patient_client(run.opcua_url, 70)
        client.set_user("operator")
        client.set_password(run.token)
        async with client:
            ns = await client.get_namespace_index(NS_URI)
            program = client.get_node(ua.NodeId("PLC.Program", ns))
            name = method if method.startswith("0:") else f"{ns}:{method}"
            t0 = time.monotonic()
            try:
                result = await program.call_method(name, *args)
            except ua.UaStatusCodeError as exc:
                kind = ("refused" if type(exc).__name__ in ("BadInvalidState",
                                                            "BadInvalidArgument")
                        else "none")
                return Outcome(kind, None, time.monotonic() - t0, type(exc).__name__)
            state = str(result[1]) if isinstance(result, list) and len(result) > 1 else None
            return Outcome("applied", state, time.monotonic() - t0, str(result))
    return asyncio.run(asyncio.wait_for(call(), 90))


def opcua_command(run: Run, command: str) -> Outcome:
    return _opcua_call(run, OPCUA_METHODS[command])


def opcua_download(run: Run, text: str, online: bool, name: str) -> Outcome:
    return _opcua_call(run, "Download", text, online, name)


# -- HTTP and the CLI -----------------------------------------------------------------------

def _from_http(t0: float, call: Any) -> Outcome:
    try:
        reply = call()
    except ApiError as exc:
        kind = "expired" if "expired" in exc.message else (
            "refused" if exc.status in (409, 422) else "none")
        return Outcome(kind, None, time.monotonic() - t0,
                       f"{exc.status} {exc.message} {list(exc.problems)}")
    except (ApiUnreachable, OSError) as exc:
        return Outcome("none", None, time.monotonic() - t0, repr(exc))
    if "outcome" in reply and not reply.get("ok"):
        return Outcome("pending", None, time.monotonic() - t0, str(reply))
    kind = "applied" if reply.get("ok", True) else "refused"
    return Outcome(kind, reply.get("state"), time.monotonic() - t0, str(reply)[:300])


def http_command(run: Run, command: str) -> Outcome:
    return _from_http(time.monotonic(), lambda: run.api.command(command))


def http_download(run: Run, text: str, online: bool, name: str,
                  dry_run: bool = False) -> tuple[Outcome, dict[str, Any]]:
    plan: dict[str, Any] = {}

    def call() -> dict[str, Any]:
        reply = run.api.download_text(text, online=online, name=name, dry_run=dry_run)
        plan.update(reply.get("plan") or {})
        return reply

    # The client waits up to 65 s (the contract's 60 s deadline); the test gives up at 25 s.
    t0, result = time.monotonic(), list[Outcome]()
    sender = threading.Thread(target=lambda: result.append(_from_http(t0, call)), daemon=True)
    sender.start()
    sender.join(DOWNLOAD_GIVE_UP_S)
    if not result:
        return Outcome("none", None, time.monotonic() - t0, "no answer (download hangs)"), plan
    return result[0], plan


def cli(run: Run, *args: str, timeout_s: float = 30.0) -> Outcome:
    """`softplc ARGS --api URL --state-dir DIR` as a process: exit 0 applied, 1 refused,
    2 unreachable."""
    t0 = time.monotonic()
    try:
        done = subprocess.run([sys.executable, "-m", "softplc.cli", *args, "--api", run.api_url,
                               "--state-dir", str(run.state_dir)], cwd=ROOT,
                              capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return Outcome("none", None, time.monotonic() - t0, "the CLI did not return")
    kind = {0: "applied", 1: "refused"}.get(done.returncode, "none")
    text = (done.stdout + done.stderr).strip()
    if kind == "refused" and "expired" in text:
        kind = "expired"
    return Outcome(kind, None, time.monotonic() - t0, text[-300:])
