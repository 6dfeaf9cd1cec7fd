"""The cell case study (issue 14): three real `softplc run` processes on loopback, the cell
controller orchestrating the transport and drilling PLCs over OPC UA on their simulated plants.
Bounded: two parts delivered, then the feed ends and the cell must drain within the timeout."""

from __future__ import annotations

import asyncio
from pathlib import Path

from asyncua import Client, ua

from softplc.opcua.cell import CellRun, watch

TIMEOUT_S = 240.0  # ~40 s on an idle machine (two transport runs and drilling cycles)
LAG_BOUND_S = 90.0  # delivery to drilled, per part: a drilling cycle is ~15 s of plant time


def test_every_part_transported_and_drilled(tmp_path: Path) -> None:
    lines: list[str] = []
    with CellRun(tmp_path) as run:
        report = asyncio.run(watch(run, parts=2, timeout_s=TIMEOUT_S, say=lines.append))
        logs = {name: run.log_tail(name) for name in ("transport", "drilling", "cell")}
    trail = "\n".join(lines) + "\n" + "\n".join(f"--- {k}\n{v}" for k, v in logs.items())
    assert report.drained, trail
    assert not report.breaches, trail  # never a part drilled that was not delivered
    assert not report.faults, trail
    assert len(report.delivered_at) >= 2
    assert len(report.drilled_at) == len(report.delivered_at), trail
    assert report.worst_lag_s() < LAG_BOUND_S, trail
    last = report.last
    assert last is not None
    # The cell counted what the two PLCs did, one release per delivered part.
    assert last.values[("cell", "parts_released")] == len(report.delivered_at)
    assert last.values[("cell", "parts_delivered")] == len(report.delivered_at)


async def _refusal(run: CellRun) -> tuple[int, bool, str, str]:
    clients = {name: Client(run.url(name), timeout=5) for name in ("transport", "cell")}
    for client in clients.values():
        await client.connect()
    try:
        ns = {k: await c.get_namespace_index("urn:softplc") for k, c in clients.items()}
        refused = clients["cell"].get_node(ua.NodeId("PLC.Marking.refused", ns["cell"]))
        for _ in range(600):  # 60 s at most
            try:
                if await refused.read_value():
                    break
            except ua.UaStatusCodeError:  # the place's node appears once it is marked
                pass
            await asyncio.sleep(0.1)
        await asyncio.sleep(0.5)  # the cell's outputs reach the transport PLC
        hold = clients["transport"].get_node(ua.NodeId("PLC.Symbols.hold", ns["transport"]))
        m_state = clients["cell"].get_node(ua.NodeId("PLC.Status.State", ns["cell"]))
        t_state = clients["transport"].get_node(ua.NodeId("PLC.Status.State", ns["transport"]))
        return (int(await refused.read_value()), bool(await hold.read_value()),
                str(await t_state.read_value()), str(await m_state.read_value()))
    finally:
        for client in clients.values():
            await client.disconnect()


def test_refused_start_is_an_event_not_a_crash(tmp_path: Path) -> None:
    # The remote PLCs are started already: the cell's Start calls are refused (BadInvalidState).
    with CellRun(tmp_path, start_remotes=True) as run:
        marked, hold, remote, state = asyncio.run(_refusal(run))
        alive = all(proc.poll() is None for proc in run.procs.values())
        log = run.log_tail("cell")
    assert marked == 1, log  # the net went to `refused` (and emitted start_refused)
    assert remote == "RUNNING", log  # the refusal changed nothing on the remote side
    assert hold, log  # ... where it holds the transport's feed
    assert state == "RUNNING", log  # the cell itself keeps scanning
    assert alive
