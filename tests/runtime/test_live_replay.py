"""A live trace with Modbus remote I/O replays bit for bit (issue 26.6).

The real ScanLoop, stepped scan by scan on the real clock, with a trace file; its remote I/O
is a real pymodbus server (tests/devices/remote_io_device.py). The live loop opens the devices
of its program after the scan that downloads it, so that scan observed no device; the trace
did not say so and replay judged the device answering there, then faulted the PLC when the
device had not answered yet at the next scan: "first divergence at scan 1 ... pump recorded 1,
replay 0". Every wait is bounded in scans."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.debug.replay import replay
from softplc.program.compiler import compile_file
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.trace import read_trace
from tests.devices.remote_io_device import FC_DI, RemoteIoDevice

MAX_SCANS = 2000  # about 6 s at the gap below: far beyond any wait here
SCAN_GAP_S = 0.002

IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: 0.1,
         reconnect_min_s: 0.05, reconnect_max_s: 0.1, startup_s: 2}}
symbols:
  start: {{address: "%IX0.0", channel: "di:0"}}
  pump: {{address: "%QX0.0", channel: "coil:0", safe: false}}
"""

PROGRAM = """\
program: pump
io_image: io.yaml
places:
  idle: {tokens: 1}
  running: {outputs: [pump]}
transitions:
  go: {from: [idle], to: [running], when: start}
  halt: {from: [running], to: [idle], when: not start}
"""


def _until(loop: ScanLoop, cond: Callable[[], bool]) -> None:
    for _ in range(MAX_SCANS):
        loop.scan_once(time.monotonic_ns())
        time.sleep(SCAN_GAP_S)
        if cond():
            return
    raise AssertionError(f"not reached in {MAX_SCANS} scans")


def test_live_trace_with_modbus_remote_io_replays(tmp_path: Path) -> None:
    device = RemoteIoDevice(latency_s=0.02).start()  # a first answer takes a few scans
    (tmp_path / "io.yaml").write_text(IO.format(port=device.port), encoding="utf-8")
    program = tmp_path / "pump.yaml"
    program.write_text(PROGRAM, encoding="utf-8")
    trace = tmp_path / "live.jsonl"
    device.set(FC_DI, 0, [True])  # the pump is wanted from the first scan on
    loop = ScanLoop(LoopConfig(program=str(program), start=True, trace=str(trace)), None, None)
    try:
        _until(loop, lambda: device.coil(0))  # the device answered; the program started it
        device.set(FC_DI, 0, [False])
        _until(loop, lambda: not device.coil(0))
        device.stop()  # the device goes away: the PLC faults
        _until(loop, lambda: loop.runner.plc.state is PlcState.FAULTED)
        device.start()
        device.set(FC_DI, 0, [True])
        _until(loop, lambda: loop.runner.device_report()["rio"]["verdict"] == "ok")
        loop.pending += [ProgramCommand(Command.RESET), ProgramCommand(Command.START)]
        _until(loop, lambda: device.coil(0))
    finally:
        loop.shutdown()
        device.dispose()
    plc = loop.runner.plc
    assert plc.state is PlcState.RUNNING
    records = list(read_trace(trace))
    fired = [name for record in records for name in record.get("fired", [])]
    assert fired == ["go", "halt", "go"]  # the trace holds what the program did
    faults = [r["k"] for r in records if "plc_fault:device" in r.get("ev", [])]
    assert len(faults) == 1
    result = replay(trace, compile_file(str(program)))
    assert result.divergence is None
    assert result.scans == len(records)
    # The download's scan ran before the program's device was opened, and the trace says so.
    assert records[0]["obs"]["devs"] == []
    assert json.dumps(records[1:]).count('"devs": []') == 0
