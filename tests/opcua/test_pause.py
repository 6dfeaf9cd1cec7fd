"""A paused PLC (breakpoints, docs/debug.md) as OPC UA shows it: PLC.Status.Paused and
PauseReason follow the pause while State stays RUNNING, against a real `softplc run` whose
breakpoint is set over its HTTP API (issue 32: status, the page and OPC UA show the pause)."""

from __future__ import annotations

import asyncio
from pathlib import Path

from asyncua import Client, ua

from softplc.api.client import ApiClient
from tests.opcua.conftest import patient_client, start_plc, stop_plc
from tests.support import free_port

TIMEOUT_S = 60.0
Seen = tuple[bool, str, str]


async def _status(client: Client, ns: int) -> Seen:
    values = [await client.get_node(ua.NodeId(f"PLC.Status.{name}", ns)).read_value()
              for name in ("Paused", "PauseReason", "State")]
    return bool(values[0]), str(values[1]), str(values[2])


async def _until(client: Client, ns: int, paused: bool) -> Seen:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + TIMEOUT_S
    while True:
        seen = await _status(client, ns)
        if seen[0] is paused or loop.time() > deadline:
            return seen
        await asyncio.sleep(0.1)


def test_opc_ua_shows_the_pause_of_a_breakpoint_and_its_end(tmp_path: Path) -> None:
    api_port = free_port()
    plc = start_plc("programs/transport.yaml", tmp_path, "--api", f"127.0.0.1:{api_port}",
                    plant="transport")
    api = ApiClient(f"http://127.0.0.1:{api_port}", state_dir=tmp_path, timeout_s=10)

    async def scenario() -> list[Seen]:
        async with patient_client(plc.url) as client:
            ns = await client.get_namespace_index("urn:softplc")
            seen = [await _status(client, ns)]
            assert api.add_breakpoint("enabled", "c1.start")["breakpoint"] == "b1"
            seen.append(await _until(client, ns, paused=True))
            api.remove_breakpoint()
            api.continue_()
            seen.append(await _until(client, ns, paused=False))
            return seen

    try:
        before, during, after = asyncio.run(scenario())
    finally:
        stop_plc(plc.proc)
    assert before == (False, "", "RUNNING")
    assert during == (True, "b1: c1.start becomes enabled", "RUNNING")
    assert after == (False, "", "RUNNING")
