"""Start-up like a PLC (issue 26): no firing round before every device's first input image,
the `first_scan` bit, threshold events already past at a start.

The pure scan only: the device answers are the Observed the runtime would hand it, the drivers
the runtime has open are `Plc.open_devices`. No socket, no clock, no sleep.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.core.image import ProcessImage
from softplc.core.judge import Observed
from softplc.core.lifecycle import Command, PlcState
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.problems import FaultCode
from softplc.core.result import ScanResult
from softplc.core.scan import scan
from softplc.program.compiler import compile_text

MS = 1_000_000
IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: 1502, {policy}}}
symbols:
  part:  {{address: "%IX0.0", channel: "di:0"}}
  level: {{address: "%IW0", type: word, channel: "ir:0"}}
  pump:  {{address: "%QX0.0", channel: "coil:0", safe: false}}
  lamp:  {{address: "%QX0.1", channel: "coil:1", safe: false}}
  seen:  {{address: "%MX0.0"}}
  first: {{address: "%MW0", type: word}}
events:
  high: {{above: level, threshold: 400, hysteresis: 50}}
  empty: {{below: level, threshold: 100}}
"""
# The reported program: a transition on "not an input" and one on a low level, both wrong on
# an image nobody has read yet (part and level are 1 and 500 at the device).
PROGRAM = """\
program: startup
io_image: io.yaml
places:
  idle: {tokens: 1}
  run: {outputs: [pump]}
  alarm: {}
transitions:
  go:    {from: [idle], to: [run], when: "not part"}
  low:   {from: [idle], to: [run], when: "level < 100"}
  alert: {to: [alarm], when: high, priority: 5}
  init:  {when: first_scan, do: ["first = first + 1", set seen]}
"""


def compile_startup(tmp_path: Path, program: str = PROGRAM,
                    policy: str = "startup_s: 1") -> CompiledNet:
    (tmp_path / "io.yaml").write_text(IO.format(policy=policy), encoding="utf-8")
    return compile_text(program, str(tmp_path / "startup.yaml"))


class Rig:
    """A PLC whose runtime has `rio` open (as declared) and reports its answers."""

    def __init__(self, net: CompiledNet, answering: bool = False) -> None:
        self.net = net
        self.plc = Plc.empty(ProcessImage(net.io.sizes))
        self.plc.open_devices = {"rio": net.io.drivers["rio"]}
        self.inputs = ProcessImage(net.io.sizes)
        self.answering = answering
        self.results: list[ScanResult] = []
        self.scan(0, [ProgramCommand(Command.DOWNLOAD, net), ProgramCommand(Command.START)])

    def deliver(self, **values: int) -> None:
        """The device's first input image arrives (the driver copies it, then answers)."""
        for name, value in values.items():
            self.inputs.set(self.net.io.symbols[name].address, value)
        self.answering = True

    def scan(self, now_ns: int, commands: list[ProgramCommand] | None = None) -> ScanResult:
        observed = Observed({"rio": self.answering},
                            {} if self.answering else {"rio": "no cycle completed yet"})
        result = scan(self.plc, self.inputs, now_ns, commands or [], (), observed)
        self.results.append(result)
        return result

    def get(self, name: str) -> int:
        return self.plc.image.get(self.net.io.symbols[name].address)

    def fired(self) -> list[str]:
        return [name for r in self.results for name in r.fired]


def test_no_round_before_the_first_input_image(tmp_path: Path) -> None:
    rig = Rig(compile_startup(tmp_path))
    for k in range(1, 20):  # the remote I/O takes 20 scans for its first cycle
        rig.scan(k * 10 * MS)
        assert rig.plc.state is PlcState.RUNNING
        assert rig.plc.waiting_io == ("rio",)
        assert rig.get("pump") == 0 and rig.get("lamp") == 0  # safe
    assert rig.fired() == [] and rig.plc.marking() == {"idle": 1}
    assert all(r.events == () for r in rig.results)  # conditions are not judged on zeros
    rig.deliver(part=1, level=500)
    result = rig.scan(200 * MS)
    assert rig.plc.waiting_io == ()
    # the first round sees the device's values: neither `go` nor `low`; high is already past
    assert result.fired == ("alert", "init") and result.events == ("high",)
    for k in range(21, 30):
        rig.scan(k * 10 * MS)
    assert "go" not in rig.fired() and "low" not in rig.fired()
    assert rig.get("pump") == 0


def test_a_driver_not_opened_yet_is_waited_for(tmp_path: Path) -> None:
    # The runtime opens a download's devices after the scan that applies it (issue 26.6).
    net = compile_startup(tmp_path)
    plc = Plc.empty(ProcessImage(net.io.sizes))
    plc.open_devices = {}
    inputs = ProcessImage(net.io.sizes)
    first = scan(plc, inputs, 0, [ProgramCommand(Command.DOWNLOAD, net),
                                  ProgramCommand(Command.START)])
    assert first.fired == () and plc.waiting_io == ("rio",) and plc.state is PlcState.RUNNING
    plc.open_devices = {"rio": net.io.drivers["rio"]}
    inputs.set(net.io.symbols["part"].address, 1)
    inputs.set(net.io.symbols["level"].address, 200)
    second = scan(plc, inputs, 10 * MS, (), (), Observed({"rio": True}))
    assert second.fired == ("init",) and not plc.waiting_io


def test_a_driver_opened_from_another_spec_is_not_this_programs(tmp_path: Path) -> None:
    net = compile_startup(tmp_path)
    (tmp_path / "other").mkdir()
    other = compile_startup(tmp_path / "other", policy="startup_s: 2").io.drivers["rio"]
    plc = Plc.empty(ProcessImage(net.io.sizes))
    plc.open_devices = {"rio": other}
    scan(plc, ProcessImage(net.io.sizes), 0, [ProgramCommand(Command.DOWNLOAD, net),
                                              ProgramCommand(Command.START)],
         (), Observed({"rio": True}))
    assert plc.waiting_io == ("rio",) and plc.engine is not None
    assert plc.marking() == {"idle": 1}


def test_without_a_device_layer_the_callers_image_is_the_input(tmp_path: Path) -> None:
    # scan() from a REPL or a test: no runtime, no drivers open, nothing observed.
    net = compile_startup(tmp_path)
    plc = Plc.empty(ProcessImage(net.io.sizes))
    result = scan(plc, ProcessImage(net.io.sizes), 0,
                  [ProgramCommand(Command.DOWNLOAD, net), ProgramCommand(Command.START)])
    assert plc.open_devices is None and plc.waiting_io == ()
    assert set(result.fired) == {"go", "init"}  # `go` wins `idle` by declaration order


@pytest.mark.parametrize(("policy", "silent_scans"), [
    ("on_failure: fault", 0),
    ("on_failure: hold, hold_scans: 3", 3),
])
def test_a_device_that_never_delivers_is_decided_by_its_policy(
        tmp_path: Path, policy: str, silent_scans: int) -> None:
    rig = Rig(compile_startup(tmp_path, policy=f"startup_s: 0.5, {policy}"))
    k = 0
    while rig.plc.state is PlcState.RUNNING and k < 200:
        k += 1
        rig.scan(k * 10 * MS)
        assert rig.get("pump") == 0
    assert rig.plc.state is PlcState.FAULTED and rig.plc.fault_code == FaultCode.DEVICE
    # 0.5 s of start-up grace (scans 1..49), then the policy: at once, or after the hold
    assert k == 50 + silent_scans
    assert rig.fired() == []
    assert "not answering" in rig.plc.fault_reason and rig.plc.waiting_io == ()


def test_timers_do_not_run_while_waiting(tmp_path: Path) -> None:
    program = PROGRAM.replace('when: "not part"}', 'when: "not part", delay: 100ms}')
    rig = Rig(compile_startup(tmp_path, program))
    rig.deliver(part=0, level=200)
    rig.scan(10 * MS)  # go becomes a candidate: its delay starts
    rig.plc.devices.forget()  # the runtime swapped in other drivers: their first image again
    rig.answering = False
    for k in range(2, 100):
        rig.scan(k * 10 * MS)
        assert rig.plc.waiting_io == ("rio",) and rig.get("pump") == 0
    rig.answering = True
    for k in range(100, 120):  # 10 ms of the delay ran before the wait: 90 ms are left
        if "go" in rig.scan(k * 10 * MS).fired:
            break
    assert k == 109, f"go fired in scan {k}"


def test_outputs_come_back_when_a_wait_ends(tmp_path: Path) -> None:
    program = PROGRAM.replace('do: ["first = first + 1", set seen]',
                              'do: ["first = first + 1", set seen, set lamp]')
    rig = Rig(compile_startup(tmp_path, program))
    rig.deliver(part=1, level=200)
    rig.scan(10 * MS)
    assert rig.get("lamp") == 1  # set by an action: Mealy, not given back by the marking
    rig.plc.devices.forget()
    rig.answering = False
    rig.scan(20 * MS)
    assert rig.get("lamp") == 0 and rig.plc.state is PlcState.RUNNING
    rig.answering = True
    rig.scan(30 * MS)
    assert rig.get("lamp") == 1 and rig.plc.io_wait is None


def test_first_scan_is_true_in_the_first_round_of_every_start(tmp_path: Path) -> None:
    rig = Rig(compile_startup(tmp_path))
    rig.scan(10 * MS)  # still waiting: the first round has not run, first_scan is not spent
    rig.deliver(part=1, level=200)
    for k in range(2, 6):
        rig.scan(k * 10 * MS)
    assert rig.get("first") == 1 and rig.fired().count("init") == 1
    rig.scan(60 * MS, [ProgramCommand(Command.STOP)])
    rig.scan(70 * MS, [ProgramCommand(Command.RESUME)])  # a warm start
    rig.scan(80 * MS)
    assert rig.get("first") == 2
    rig.scan(90 * MS, [ProgramCommand(Command.STOP)])
    rig.scan(100 * MS, [ProgramCommand(Command.RESET)])
    rig.scan(110 * MS, [ProgramCommand(Command.START)])  # a cold start
    rig.scan(120 * MS)
    assert rig.get("first") == 3 and rig.fired().count("init") == 3


def test_a_threshold_still_past_at_a_resume_is_an_event_again(tmp_path: Path) -> None:
    rig = Rig(compile_startup(tmp_path))
    rig.deliver(part=1, level=500)
    assert rig.scan(10 * MS).events == ("high",)
    assert rig.scan(20 * MS).events == ()  # armed again only below 350
    rig.scan(30 * MS, [ProgramCommand(Command.STOP)])
    result = rig.scan(40 * MS, [ProgramCommand(Command.RESUME)])
    assert result.events == ("high",) and "alert" in result.fired


def test_a_threshold_crossed_later_still_needs_its_hysteresis(tmp_path: Path) -> None:
    rig = Rig(compile_startup(tmp_path))
    rig.deliver(part=1, level=200)
    seen = []
    for k, level in enumerate([200, 450, 380, 420, 340, 401, 50], 1):
        rig.inputs.set(rig.net.io.symbols["level"].address, level)
        seen.append(rig.scan(k * 10 * MS).events)
    assert seen == [(), ("high",), (), (), (), ("high",), ("empty",)]
