"""Benchmark section `opcua`: what OPC UA clients get from a running PLC and cost its scan, and
how long a remote component's call takes to show on the other PLC's outputs.

Keys: `reads_per_s` (one asyncua client reading a symbol, request after request),
`notifications_per_s` (data-change notifications received by 4 clients subscribed to every
symbol of the transport program), `p99_ratio_over_floor_1ms` (scan p99 lateness at 1 ms while
the 4 clients are subscribed / the empty-loop floor of the same run), `call_to_effect_scans`
(median; `call_to_effect_scans_max`): a caller scanning at 10 ms with the `kind: opcua`
driver raises a `call:PLC.Program.Start` output; counted in the caller's scans until its
input bound to the callee's output `lamp` (on in the callee's first running scan) reads 1.
Owns: the subscribed clients' process, the caller loop, the section's keys.
Does not know: how the runtime starts (live.py), the server's internals.
"""

from __future__ import annotations

import asyncio
import logging
import os
import statistics
import tempfile
import time
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Final

from asyncua import Client

from softplc.bench.live import LiveRuntime, run_floor
from softplc.bench.load import client_process
from softplc.bench.measure import Progress, ratio
from softplc.bench.scanbench import SETTLE_S, window_figures
from softplc.core.image import ProcessImage
from softplc.opcua.driver import OpcUaIoDriver
from softplc.opcua.ids import string_id
from softplc.program.io_image import parse_io_image
from softplc.runtime.realtime import Realtime, recommended

CLIENTS: Final = 4
SUBSCRIPTION_MS: Final = 50.0  # an HMI's refresh rate
CALLER_PERIOD_S: Final = 0.01
TOKEN_ENV: Final = "SOFTPLC_BENCH_OPCUA_TOKEN"
LAMP_PROGRAM: Final = """program: lamp
io_image: lamp_io.yaml
places:
  lit: {tokens: 1, outputs: [lamp]}   # on from the first running scan
"""
LAMP_IO: Final = """symbols:
  lamp: {address: "%QX0.0", type: bool, safe: false, driver: none}
"""
CALLER_IO: Final = """drivers:
  far: {{kind: opcua, url: "opc.tcp://127.0.0.1:{port}", user: bench, password_env: {env}}}
symbols:
  lamp_far:   {{address: "%IX0.0", type: bool, channel: PLC.Symbols.lamp}}
  start_done: {{address: "%IX0.1", type: bool, channel: "done:start"}}
  stop_done:  {{address: "%IX0.2", type: bool, channel: "done:stop"}}
  resume_done: {{address: "%IX0.3", type: bool, channel: "done:resume"}}
  start:      {{address: "%QX0.0", type: bool, channel: "call:PLC.Program.Start"}}
  stop:       {{address: "%QX0.1", type: bool, channel: "call:PLC.Program.Suspend"}}
  resume:     {{address: "%QX0.2", type: bool, channel: "call:PLC.Program.Resume"}}
"""


class _Counter:
    """asyncua subscription handler: counts data-change notifications."""

    def __init__(self) -> None:
        self.count = 0

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.count += 1


async def _clients(url: str, duration_s: float) -> dict[str, Any]:
    # asyncua warns when the server revises a session timeout or a subscription's intervals
    # (it does, as servers may): in a benchmark's output that is noise, not news.
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    clients = [Client(url, timeout=10) for _ in range(CLIENTS)]
    counters = [_Counter() for _ in clients]
    for client in clients:
        await client.connect()
    try:
        ns = await clients[0].get_namespace_index("urn:softplc")
        for client, counter in zip(clients, counters, strict=True):
            folder = client.get_node(string_id("PLC.Symbols", ns))
            subscription = await client.create_subscription(SUBSCRIPTION_MS, counter)
            await subscription.subscribe_data_change(await folder.get_children())
        await asyncio.sleep(0.5)  # the initial values arrive first: not counted
        before = sum(c.count for c in counters)
        t0 = time.monotonic_ns()
        await asyncio.sleep(duration_s)
        t1 = time.monotonic_ns()
        notifications = sum(c.count for c in counters) - before
        node = clients[0].get_node(string_id("PLC.Symbols.s1_i", ns))
        reads, r0 = 0, time.monotonic()
        while time.monotonic() - r0 < duration_s / 2:
            await node.read_value()
            reads += 1
        reads_s = time.monotonic() - r0
    finally:
        for client in clients:
            await client.disconnect()
    return {"t0_ns": t0, "t1_ns": t1, "notifications": notifications,
            "reads": reads, "reads_s": reads_s}


def clients_main(url: str, duration_s: float, results: Connection) -> None:
    """The clients' process (as an HMI/SCADA would be, off the PLC's processes)."""
    results.send(asyncio.run(_clients(url, duration_s)))


def _subscribed(runtime: LiveRuntime, duration_s: float, realtime: Realtime) -> dict[str, Any]:
    url = f"opc.tcp://127.0.0.1:{runtime.opcua_port}"
    return client_process(clients_main, (url, duration_s), "opcua-clients", realtime,
                          2 * duration_s + 60, "the OPC UA clients")


def _load(duration_s: float, realtime: Realtime, progress: Progress) -> dict[str, Any]:
    runtime = LiveRuntime(period_ns=1_000_000, capacity_s=3 * duration_s + 60,
                          realtime=realtime, modbus=False, api=False, opcua=True)
    try:
        progress(f"opcua: transport at 1 ms with {CLIENTS} subscribed clients, {duration_s:g} s")
        runtime.start()
        runtime.wait_for_state("RUNNING")
        time.sleep(SETTLE_S)
        clients = _subscribed(runtime, duration_s, realtime)
        record = runtime.stop()
    finally:
        runtime.stop()
    assert record is not None
    seconds = (clients["t1_ns"] - clients["t0_ns"]) / 1e9
    return {**window_figures(record.window(clients["t0_ns"], clients["t1_ns"])),
            "notifications_per_s": clients["notifications"] / seconds,
            "reads_per_s": clients["reads"] / clients["reads_s"]}


def _scans_until(driver: OpcUaIoDriver, image: ProcessImage, address: Any, want: int,
                 limit: int) -> int:
    """Caller scans (read inputs, write outputs, sleep a period) until image[address] == want."""
    for n in range(1, limit + 1):
        driver.write_outputs(image, 0)
        time.sleep(CALLER_PERIOD_S)
        driver.read_inputs(image, 0)
        if image.get(address) == want:
            return n
    raise RuntimeError(f"no effect within {limit} caller scans")


def _call_to_effect(repeats: int, realtime: Realtime, progress: Progress) -> list[int]:
    progress(f"opcua: call-to-effect, {repeats} Start/Resume calls at 10 ms")
    with tempfile.TemporaryDirectory(prefix="softplc-bench-lamp-") as tmp:
        (Path(tmp) / "lamp.yaml").write_text(LAMP_PROGRAM)
        (Path(tmp) / "lamp_io.yaml").write_text(LAMP_IO)
        runtime = LiveRuntime(Path(tmp) / "lamp.yaml", period_ns=10_000_000, start=False,
                              plant=None, realtime=realtime, modbus=False, api=False,
                              opcua=True, record=False)
        try:
            runtime.start()
            runtime.wait_for_state("STOPPED")
            token_file = Path(runtime._state_dir.name) / "api_token"
            os.environ[TOKEN_ENV] = token_file.read_text().strip()
            return _calls(runtime, repeats)
        finally:
            runtime.stop()


def _calls(runtime: LiveRuntime, repeats: int) -> list[int]:
    io = parse_io_image(CALLER_IO.format(port=runtime.opcua_port, env=TOKEN_ENV), "caller.yaml")
    driver = OpcUaIoDriver(io.drivers["far"], list(io.symbols.values()))
    image, sym = ProcessImage(io.sizes), {k: s.address for k, s in io.symbols.items()}
    driver.open()
    try:
        deadline = time.monotonic() + 60
        while driver.problem() and time.monotonic() < deadline:
            time.sleep(0.05)
        scans = []
        for k in range(repeats):
            # Part 10: Start from Ready (the first time), Resume from Suspended (after that).
            call, done = ("start", "start_done") if k == 0 else ("resume", "resume_done")
            image.set(sym[call], 1)  # the rising edge: the call is issued
            scans.append(_scans_until(driver, image, sym["lamp_far"], 1, 2000))
            _scans_until(driver, image, sym[done], 1, 2000)
            image.set(sym[call], 0)
            image.set(sym["stop"], 1)  # Suspend: the lamp goes to its safe value, off
            _scans_until(driver, image, sym["lamp_far"], 0, 2000)
            _scans_until(driver, image, sym["stop_done"], 1, 2000)
            image.set(sym["stop"], 0)
            _scans_until(driver, image, sym["stop_done"], 0, 2000)
        return scans
    finally:
        driver.close()


def run(quick: bool, progress: Progress, *, duration_s: float | None = None,
        realtime: Realtime | None = None) -> dict[str, Any]:
    duration = duration_s if duration_s is not None else (1.5 if quick else 20.0)
    realtime = recommended() if realtime is None else realtime
    load_before = os.getloadavg()
    result: dict[str, Any] = {"duration_s": duration, "clients": CLIENTS,
                              "subscription_ms": SUBSCRIPTION_MS,
                              "program": "programs/transport.yaml (plant transport, started)"}
    progress(f"opcua: floor (empty loop) at 1 ms, {duration:g} s")
    floor = window_figures(run_floor(1_000_000, duration, realtime))
    result["floor_1ms"] = floor
    loaded = _load(duration, realtime, progress)
    result["subscribed_1ms"] = loaded
    result["p99_ratio_over_floor_1ms"] = ratio(loaded["lateness_us"]["p99"],
                                               floor["lateness_us"]["p99"])
    result["overruns_1ms"] = loaded["overruns"]
    result["reads_per_s"] = loaded["reads_per_s"]
    result["notifications_per_s"] = loaded["notifications_per_s"]
    scans = _call_to_effect(3 if quick else 20, realtime, progress)
    result["call_to_effect"] = {"caller_period_ms": CALLER_PERIOD_S * 1000,
                                "callee_period_ms": 10, "scans": scans}
    result["call_to_effect_scans"] = statistics.median(scans)
    result["call_to_effect_scans_max"] = max(scans)
    result["load_average_1m"] = [load_before[0], os.getloadavg()[0]]
    return result
