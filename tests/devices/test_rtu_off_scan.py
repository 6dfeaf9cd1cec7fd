"""A silent Modbus RTU unit never stalls the scan (issue 39, item 4): a real ScanLoop on its
own clock, a socat pty pair with a pymodbus RTU server (tests/devices/rtu_line.py), and a unit
that stops answering. The fault scan used to wait 0.2 s for a safe write the silent unit could
not confirm (two overruns at a 150 ms period); now the scans keep their slots, and the fault
reason says what happened in the PLC's words. Every wait is bounded by a deadline."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.core.lifecycle import PlcState
from softplc.runtime.config import LoopConfig
from softplc.runtime.loop import ScanLoop
from tests.devices.rtu_line import RtuLine
from tests.support import eventually

PERIOD_NS = 150_000_000  # under the 0.2 s the old fault scan waited: it overran every time

IO = """\
drivers:
  rio: {{kind: modbus_rtu, port: {port}, unit: 1, timeout_s: 0.1, reconnect_min_s: 0.05,
        reconnect_max_s: 0.1, startup_s: 3}}
symbols:
  part: {{address: "%IX0.0", channel: "di:0", driver: rio}}
  lamp: {{address: "%QX0.0", channel: "coil:0", safe: false, driver: rio}}
"""

PROGRAM = """\
program: lamp
io_image: io.yaml
places:
  on: {tokens: 1, outputs: [lamp]}
"""


@pytest.fixture
def line(tmp_path: Path) -> Iterator[RtuLine]:
    rtu = RtuLine(tmp_path, units=(1,)).start()
    yield rtu
    rtu.dispose()


def test_a_silent_unit_faults_the_plc_without_an_overrun(line: RtuLine, tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO.format(port=line.master), encoding="utf-8")
    (tmp_path / "lamp.yaml").write_text(PROGRAM, encoding="utf-8")
    loop = ScanLoop(LoopConfig(program=str(tmp_path / "lamp.yaml"), start=True,
                               period_ns=PERIOD_NS), None, None)
    plc, stop = loop.runner.plc, threading.Event()
    runner = threading.Thread(target=loop.run, args=(stop,), name="scan", daemon=True)
    runner.start()
    try:
        eventually(lambda: plc.state is PlcState.RUNNING and line.coil(1, 0), 10.0,
                   what="the lamp on", step_s=0.02)
        # Start-up scans (compile, first connect) may overrun on a busy machine: count after.
        overruns, scans = loop.stats.overruns, loop.stats.scans
        line.mute(1)
        eventually(lambda: plc.state is PlcState.FAULTED, 10.0, what="the fault", step_s=0.02)
        faulted_at = loop.stats.scans
        eventually(lambda: loop.stats.scans >= faulted_at + 3, 5.0, what="scans after it",
                   step_s=0.02)
        assert loop.stats.scans > scans + 3
        assert loop.stats.overruns == overruns, (
            f"{loop.stats.overruns - overruns} overrun(s), longest scan "
            f"{loop.stats.max_exec_ns / 1e6:.0f} ms")
        said = f"unit 1 on {line.master} did not answer within 0.1 s"
        assert plc.fault_reason == f"device rio not answering for 1 scans: {said}", \
            plc.fault_reason
        assert loop.runner.device_report()["rio"]["reason"].startswith(
            f"safe outputs not confirmed: {said}")
        # The safe image is queued: written as soon as the unit answers again.
        line.mute(1, False)
        eventually(lambda: line.coil(1, 0) is False, 5.0, what="the lamp off once it answers")
    finally:
        stop.set()
        runner.join(10)
