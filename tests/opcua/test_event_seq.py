"""LastEventSeq and the events' Seq never go back (issue 39 item 8): a client that asks for
"events since N" keeps working across a restart of the scan process. asyncua's client against
a real `softplc run` whose scan process is killed with SIGKILL; the supervisor restarts it and
its event numbers go on from the dead process's (before: they started again at 1)."""

from __future__ import annotations

import asyncio
import os
import signal
from pathlib import Path

from asyncua import Node, ua

from tests.opcua.conftest import start_plc, stop_plc
from tests.opcua.pids import api_status
from tests.opcua.test_server import Collector, _client, _node, _until
from tests.support import free_port

NS_URI = "urn:softplc"


def test_event_numbers_go_on_across_a_scan_process_restart(tmp_path: Path) -> None:
    api_port = free_port()
    plc = start_plc("programs/transport.yaml", tmp_path, "--api", f"127.0.0.1:{api_port}",
                    plant="transport")  # the plant delivers parts: part_delivered events

    async def body() -> None:
        async with _client(plc, plc.token) as client:
            ns = await client.get_namespace_index(NS_URI)
            last_seq = _node(client, ns, "PLC.Status.LastEventSeq")
            seen = Collector()
            sub = await client.create_subscription(20, seen)
            await sub.subscribe_data_change(last_seq)
            etype = await client.get_node(ua.ObjectIds.BaseEventType).get_child(
                f"{ns}:SoftplcEventType")
            await sub.subscribe_events(_node(client, ns, "PLC"), etype)
            before = await _until(lambda: _at_least(last_seq, 2))
            pid = await asyncio.to_thread(lambda: api_status(api_port, plc.token)["scan_pid"])
            assert isinstance(pid, int)
            os.kill(pid, signal.SIGKILL)
            await _until(lambda: _named(seen, "plc_restarted:1"))
            restarted = next(e for e in seen.events if e.EventName == "plc_restarted:1")
            assert restarted.Seq > before
            await _until(lambda: _at_least(last_seq, restarted.Seq))
            values = [v for node, v in seen.changes if node == "PLC.Status.LastEventSeq"]
            assert values == sorted(values) and values[-1] >= restarted.Seq, values
            await sub.delete()

    try:
        asyncio.run(body())
    finally:
        stop_plc(plc.proc)


async def _at_least(node: Node, n: int) -> int:
    value = int(await node.read_value())
    return value if value >= n else 0


async def _named(seen: Collector, name: str) -> bool:
    return name in seen.names()
