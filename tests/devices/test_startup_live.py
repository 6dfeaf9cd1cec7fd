"""Start-up like a PLC, end to end (issue 26): a scan loop whose remote I/O is a real pymodbus
server on 127.0.0.1 (tests/devices/remote_io_device.py) with inputs already set before the
start, and a latency so that its first input image takes many scans to arrive.

The loop is stepped scan by scan (ScanLoop.scan_once) on the real clock; every wait is bounded
in scans. The last test replays a start-up trace (virtual clock, sim plant, no socket)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from softplc.core.lifecycle import PlcState
from softplc.core.problems import FaultCode
from softplc.debug.replay import replay
from softplc.hmi.map import FLAG_WAITING_IO, STATUS_FLAGS, status_registers
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.devices.remote_io_device import FC_DI, FC_IR, RemoteIoDevice
from tests.support import free_port

S = PlcState
SCAN_GAP_S = 0.002
MAX_SCANS = 2000  # about 5 s at the gap above: far beyond any wait here
REPO = Path(__file__).resolve().parents[2]

IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: 0.5,
         reconnect_min_s: 0.05, reconnect_max_s: 0.1, {policy}}}
symbols:
  part:  {{address: "%IX0.0", channel: "di:0"}}
  level: {{address: "%IW0", type: word, channel: "ir:0"}}
  pump:  {{address: "%QX0.0", channel: "coil:0", safe: false}}
  lamp:  {{address: "%QX0.1", channel: "coil:1", safe: false}}
"""
# `go` and `low` are right only on an image nobody read: the device says part=1, level=500.
PROGRAM = """\
program: startup
io_image: io.yaml
places:
  idle: {tokens: 1}
  run:  {outputs: [pump]}
  seen: {outputs: [lamp]}
transitions:
  go:   {from: [idle], to: [run], when: "not part"}
  low:  {from: [idle], to: [run], when: "level < 100"}
  saw:  {from: [idle], to: [seen], when: "part and level >= 100 and first_scan"}
"""


class Rig:
    """A ScanLoop without channel or shared memory, scanned by hand; after every scan the
    device's pump coil and the PLC's status are recorded."""

    def __init__(self, tmp_path: Path, port: int, policy: str,
                 device: RemoteIoDevice | None) -> None:
        (tmp_path / "io.yaml").write_text(IO.format(port=port, policy=policy), encoding="utf-8")
        (tmp_path / "startup.yaml").write_text(PROGRAM, encoding="utf-8")
        self.loop = ScanLoop(LoopConfig(program=str(tmp_path / "startup.yaml"), start=True),
                             None, None)
        self.device = device
        self.pump_seen_on = False
        self.waiting: list[tuple[PlcState, bool, int, bool]] = []  # state, doc, flags, pump

    def scan(self) -> None:
        self.loop.scan_once(time.monotonic_ns())
        plc = self.loop.runner.plc
        if self.device is not None and self.device.coil(0):
            self.pump_seen_on = True
        if plc.image.qx[0]:
            self.pump_seen_on = True
        if plc.waiting_io:
            doc = self.loop.document()
            flags = status_registers(self.loop.status())[STATUS_FLAGS]
            self.waiting.append((plc.state, doc["waiting_for_io"], flags, bool(plc.image.qx[0])))
        time.sleep(SCAN_GAP_S)

    def until(self, cond: Callable[[], bool]) -> bool:
        for _ in range(MAX_SCANS):
            self.scan()
            if cond():
                return True
        return False

    def close(self) -> None:
        self.loop.shutdown()


@pytest.fixture
def device() -> Iterator[RemoteIoDevice]:
    dev = RemoteIoDevice(latency_s=0.03).start()
    dev.set(FC_DI, 0, [True])  # already 1 before the PLC starts
    dev.set(FC_IR, 0, [500])
    yield dev
    dev.dispose()


def test_an_input_already_on_at_start_is_read_before_any_round(tmp_path: Path,
                                                                 device: RemoteIoDevice) -> None:
    rig = Rig(tmp_path, device.port, "startup_s: 5", device)
    try:
        assert rig.until(lambda: device.coil(1)), "the program never ran on the real inputs"
        for _ in range(20):
            rig.scan()
    finally:
        rig.close()
    fired = rig.loop.runner.fired_counts
    assert fired == {"saw": 1}, fired  # in the first round (first_scan), on part=1, level=500
    assert not rig.pump_seen_on  # never written 1, neither in the image nor at the device
    # It waited, RUNNING, and said so in status and the Modbus status block, outputs safe.
    assert len(rig.waiting) >= 2, rig.waiting  # the download's scan and the first cycle's
    assert all(w == (S.RUNNING, True, FLAG_WAITING_IO, False) for w in rig.waiting), rig.waiting
    assert rig.loop.document()["waiting_for_io"] is False


@pytest.mark.parametrize("policy", ["on_failure: fault", "on_failure: hold, hold_scans: 3"])
def test_a_device_that_never_delivers_faults_after_its_start_up_time(tmp_path: Path,
                                                                     policy: str) -> None:
    rig = Rig(tmp_path, free_port(), f"startup_s: 0.3, {policy}", None)  # nobody listens
    started = time.monotonic()
    try:
        assert rig.until(lambda: rig.loop.runner.plc.state is not S.RUNNING)
    finally:
        rig.close()
    plc = rig.loop.runner.plc
    assert plc.state is S.FAULTED and plc.fault_code == FaultCode.DEVICE
    assert time.monotonic() - started >= 0.3  # not before its start-up time
    assert rig.loop.runner.fired_counts == {} and not rig.pump_seen_on
    assert rig.waiting and all(w[0] is S.RUNNING and w[1] for w in rig.waiting)
    assert "device_fault:rio" in [e["name"] for e in rig.loop.events]


def test_a_start_up_trace_replays_bit_for_bit(tmp_path: Path) -> None:
    # The scan that downloads runs before the loop opens the program's devices: it waits,
    # and the trace says so, so that replay waits in the same scan.
    program = REPO / "programs" / "transport.yaml"
    trace = tmp_path / "run.trace.jsonl"
    config = LoopConfig(program=str(program), start=True, period_ns=10_000_000, max_scans=150,
                        trace=str(trace))  # the plant's first part arrives after 1 s
    loop = ScanLoop(config, None, None, VirtualClock(0))
    loop.run()
    records = [json.loads(line) for line in trace.read_text().splitlines()]
    first = next(r for r in records if r.get("k") == 0)
    assert first["obs"]["wait"] and not first.get("fired")
    assert any(r.get("fired") for r in records)  # the program ran after the wait
    result = replay(trace, compile_file(str(program)))
    assert result.ok and result.scans == len(records), result.divergence
