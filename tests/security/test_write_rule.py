"""One rule for what a client may write, at every door (issue 38): an input belongs to its
drivers and a symbol declared `hmi_writable: false` is its program's alone, whatever the door,
role or Modbus write policy (security/writes.py).

The doors that write the image are enumerated from the code (as tests/security/test_doors.py
does for the decision points): each must apply the rule, so a new write door fails here until
it names where it does. A real `softplc run` with the default policy ("open", OpenPLC's) then
refuses a write of such a symbol through Modbus, HTTP and OPC UA alike, and the image keeps its
value; before the rule had one owner, Modbus "open" and OPC UA wrote it while HTTP refused.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from asyncua import ua

from softplc.opcua.ids import string_id
from tests.api.helpers import call
from tests.hmi.helpers import connect, request
from tests.opcua.conftest import Plc, patient_client, start_plc, stop_plc
from tests.security.test_doors import DOORS, ROOT, _modules
from tests.support import eventually, free_port

CHECKOUT = ROOT.parent
# write door -> (the module that applies the rule for it, the name it calls there)
SYMBOL_RULE: dict[str, tuple[str, str]] = {
    "api/symbols.py": ("api/symbols.py", "symbol_refusal"),
    "opcua/server.py": ("opcua/space.py", "policy_refusal"),  # AccessLevel of each symbol
    "hmi/map.py": ("runtime/serve/comm.py", "locations"),  # the Writable predicate comm.py builds
    "runtime/serve/comm.py": ("runtime/serve/comm.py", "locations"),  # ... and hands the slaves
    "sparkplug/door.py": ("sparkplug/metrics.py", "symbol_refusal"),
}
LOCKED = '  speed: {address: "%MW5", type: word, hmi_writable: false}\n'  # set by the net
WORDS = 1024  # holding registers 0..1023 are %QW, 1024.. are %MW
NS_URI = "urn:softplc"


def test_every_door_that_writes_the_image_applies_the_symbol_rule() -> None:
    modules = _modules()
    writers = {rel for rel in DOORS
               if rel in modules and ({"send_hmi_write", "HmiWrite"} & modules[rel][1])}
    assert writers == set(SYMBOL_RULE), (
        "a door that writes the image must apply security/writes.py's rule: list it in "
        f"SYMBOL_RULE with where it does ({sorted(writers ^ set(SYMBOL_RULE))})")
    for door, (where, name) in SYMBOL_RULE.items():
        assert name in modules[where][1], f"{door}: {where} no longer calls {name}"


def with_symbol(io_text: str, line: str) -> str:
    """An io image's text with a symbol's `line` added to its symbols (before `events:`)."""
    return io_text.replace("\nevents:", "\n" + line + "\nevents:", 1)


@contextlib.contextmanager
def transport_serving(tmp_path: Path, line: str) -> Iterator[tuple[Plc, str, int]]:
    """transport.yaml RUNNING from a copy of the checkout in `tmp_path`, `line` added to its
    io image's symbols, with its Modbus slave (default policy: open), HTTP API and OPC UA
    server on loopback (the PLC, the API's URL, the Modbus port); a plain-text download
    finds its io image in that copy."""
    for folder in ("programs", "io_images"):
        shutil.copytree(CHECKOUT / folder, tmp_path / folder)
    io = tmp_path / "io_images" / "transport.yaml"
    io.write_text(with_symbol(io.read_text(), line))
    state = tmp_path / "state"
    state.mkdir()
    modbus, api = free_port(), free_port()
    plc = start_plc(str(tmp_path / "programs" / "transport.yaml"), state,
                    "--modbus", f"127.0.0.1:{modbus}", "--api", f"127.0.0.1:{api}",
                    "--programs-dir", str(tmp_path / "programs"))
    try:
        url = f"http://127.0.0.1:{api}"
        eventually(lambda: _symbol(url) is not None, timeout_s=60, what="the HTTP API")
        yield plc, url, modbus
    finally:
        stop_plc(plc.proc)


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[tuple[Plc, str, int]]:
    """transport.yaml RUNNING with `speed` (%MW5) declared hmi_writable: false."""
    with transport_serving(tmp_path, LOCKED) as serving:
        yield serving


def _symbol(url: str) -> dict[str, object] | None:
    try:
        answer = call(url, "GET", "/api/v1/symbols/speed", owner=True)
    except OSError:
        return None
    return answer.body if answer.status == 200 else None  # type: ignore[no-any-return]


async def _opcua_write(plc: Plc) -> str:
    """An operator's session (the owner's key as its password) writes `hold`, then tries
    `speed`: the name of the status code that refused it."""
    client = patient_client(plc.url)
    client.set_user("operator")
    client.set_password(plc.token)
    async with client:
        ns = await client.get_namespace_index(NS_URI)
        hold = client.get_node(string_id("PLC.Symbols.hold", ns))
        await hold.write_value(ua.Variant(True, ua.VariantType.Boolean))  # the role may write
        try:
            await client.get_node(string_id("PLC.Symbols.speed", ns)).write_value(
                ua.Variant(77, ua.VariantType.UInt16))
        except ua.UaStatusCodeError as exc:
            return type(exc).__name__
        return "written"


def test_a_locked_symbol_is_refused_at_every_door(plc: tuple[Plc, str, int]) -> None:
    opcua, url, modbus = plc
    with connect(modbus) as sock:  # FC 06 to %MW5
        reply = request(sock, bytes([6]) + (WORDS + 5).to_bytes(2, "big") + (77).to_bytes(2, "big"))
        assert reply == bytes([0x86, 0x02]), reply.hex()  # illegal data address
        free = request(sock, bytes([6]) + (WORDS + 300).to_bytes(2, "big") + (9).to_bytes(2, "big"))
        assert free[0] == 6  # "open" still writes a location no symbol declares
    http = call(url, "PUT", "/api/v1/symbols/speed", json.dumps({"value": 77}),
                {"Content-Type": "application/json"}, owner=True)
    assert http.status == 403 and b"hmi_writable: false" in http.raw, http.raw
    assert asyncio.run(_opcua_write(opcua)) in ("BadNotWritable", "BadUserAccessDenied")
    shown = _symbol(url)
    assert shown is not None and shown.get("raw") == 0, shown
