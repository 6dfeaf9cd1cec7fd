"""Device fault policy end to end: a scan loop whose remote I/O is a real pymodbus 3.16 server
on 127.0.0.1, stopped (device gone) and restarted on the same port (device back).

The loop is stepped scan by scan (ScanLoop.scan_once) on the real clock, so the counts below
are scans, not times; every wait is bounded in scans and seconds."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import FAULT_DEVICE, FAULT_NONE, ProgramCommand
from softplc.hmi.map import STATUS_FAULT_CODE, STATUS_STATE, status_registers
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.devices.test_modbus_io import FC_COIL, FC_DI
from tests.support import SimModbusServer, free_port

S = PlcState
SCAN_GAP_S = 0.002
MAX_SCANS = 2000  # about 5 s at the gap above: far beyond any wait here

IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: 0.1,
         reconnect_min_s: 0.05, reconnect_max_s: 0.1, {policy}}}
symbols:
  part: {{address: "%IX0.0", channel: "di:0"}}
  lamp: {{address: "%QX0.0", channel: "coil:0", safe: false}}
"""

PROGRAM = """\
program: lamp
io_image: io.yaml
places:
  on: {tokens: 1, outputs: [lamp]}
"""


class Rig:
    """A ScanLoop without channel or shared memory, scanned by hand."""

    def __init__(self, tmp_path: Path, port: int, policy: str) -> None:
        (tmp_path / "io.yaml").write_text(IO.format(port=port, policy=policy), encoding="utf-8")
        (tmp_path / "lamp.yaml").write_text(PROGRAM, encoding="utf-8")
        self.loop = ScanLoop(LoopConfig(program=str(tmp_path / "lamp.yaml"), start=True),
                             None, None)
        self.seen: list[tuple[PlcState, str]] = []

    @property
    def plc(self):  # type: ignore[no-untyped-def]
        return self.loop.runner.plc

    def verdict(self) -> str:
        return str(self.loop.runner.device_report().get("rio", {}).get("verdict", "starting"))

    def scan(self) -> None:
        self.loop.scan_once(time.monotonic_ns())
        self.seen.append((self.plc.state, self.verdict()))
        time.sleep(SCAN_GAP_S)

    def until(self, cond: Callable[[], bool]) -> bool:
        for _ in range(MAX_SCANS):
            self.scan()
            if cond():
                return True
        return False

    def command(self, command: Command) -> None:
        self.loop.pending.append(ProgramCommand(command))
        self.scan()

    def events(self) -> list[str]:
        return [e["name"] for e in self.loop.events]

    def status_block(self) -> tuple[int, int]:
        words = status_registers(self.loop.status())
        return words[STATUS_STATE], words[STATUS_FAULT_CODE]

    def close(self) -> None:
        self.loop.shutdown()


@pytest.fixture
def remote_io() -> Iterator[SimModbusServer]:
    srv = SimModbusServer(free_port())
    srv.start()
    yield srv
    srv.dispose()


def lamp(server: SimModbusServer) -> bool:
    return bool(server.get(FC_COIL, 0, 1)[0])


def test_hold_then_fault_and_reset_after_the_device_returns(remote_io: SimModbusServer,
                                                            tmp_path: Path) -> None:
    server = remote_io
    rig = Rig(tmp_path, server.port, "on_failure: hold, hold_scans: 3")
    try:
        server.set(FC_DI, 0, [True])
        assert rig.until(lambda: rig.verdict() == "ok" and lamp(server))
        assert rig.plc.state is S.RUNNING and rig.status_block() == (int(S.RUNNING), 0)

        server.stop()
        rig.seen.clear()
        assert rig.until(lambda: rig.plc.state is S.FAULTED)
        held = [state for state, verdict in rig.seen if verdict == "holding"]
        assert held == [S.RUNNING] * 3  # then the fourth silent scan faulted
        assert rig.seen[-1] == (S.FAULTED, "fault")
        assert (rig.plc.fault_code, rig.status_block()) == (FAULT_DEVICE, (int(S.FAULTED), 2))
        assert rig.plc.fault_reason.startswith("device rio not answering for 4 scans: ")
        # The device is gone: the faulting scan's go_safe cannot be confirmed, and says so.
        assert rig.events()[-4:] == ["device_down:rio", "safe_unconfirmed:rio",
                                     "device_fault:rio", "plc_fault:device"]
        assert bool(rig.plc.image.qx[0]) is False

        server.start()  # same port, fresh data; the operator switches the coil on by hand
        server.set(FC_COIL, 0, [True])
        assert rig.until(lambda: rig.verdict() == "ok" and not lamp(server))  # safe, written
        assert rig.events()[-1] == "device_ok:rio"
        for _ in range(20):
            rig.scan()
        assert rig.plc.state is S.FAULTED  # no auto_recover: an operator must reset

        rig.command(Command.RESET)
        assert (rig.plc.state, rig.plc.fault_code) == (S.STOPPED, FAULT_NONE)
        assert rig.status_block() == (int(S.STOPPED), 0)
        rig.command(Command.START)
        assert rig.until(lambda: lamp(server))
        assert rig.plc.state is S.RUNNING
    finally:
        rig.close()


def test_fault_at_once_and_auto_recover_when_the_device_returns(remote_io: SimModbusServer,
                                                                tmp_path: Path) -> None:
    server = remote_io
    rig = Rig(tmp_path, server.port, "on_failure: fault, auto_recover: true")
    try:
        assert rig.until(lambda: rig.verdict() == "ok" and lamp(server))
        server.stop()
        rig.seen.clear()
        assert rig.until(lambda: rig.plc.state is S.FAULTED)
        assert [s for s, v in rig.seen if v != "ok"] == [S.FAULTED]  # the first silent scan
        assert rig.status_block() == (int(S.FAULTED), 2)

        server.start()
        assert rig.until(lambda: rig.plc.state is S.RUNNING)
        assert rig.events()[-2:] == ["device_ok:rio", "plc_recovered:device"]
        assert rig.status_block() == (int(S.RUNNING), 0)
        assert rig.until(lambda: lamp(server))  # the marking drives the lamp again
    finally:
        rig.close()
