"""Device fault policy through the runner: the transport case study on its simulated plant,
whose sim driver goes offline (fault injection), in virtual time. Also the policy keys of the
symbols file. No socket here: tests/devices/test_fault_policy_live.py uses a Modbus server."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import FAULT_DEVICE, FAULT_NONE, ProgramCommand
from softplc.core.problems import ProgramError
from softplc.core.result import ScanResult
from softplc.core.symbols import FaultPolicy, OnFailure
from softplc.devices.sim import SimDriver
from softplc.program.compiler import compile_file
from softplc.program.io_image import parse_io_image
from softplc.runtime.runner import boot

S = PlcState
PERIOD = 50_000_000
REPO = Path(__file__).resolve().parents[2]


def transport(tmp_path: Path, policy: str) -> Path:
    """The shipped transport program with `policy` added to its sim driver."""
    shutil.copytree(REPO / "programs", tmp_path / "programs")
    io = (REPO / "io_images" / "transport.yaml").read_text(encoding="utf-8")
    line = "plant: {kind: sim, plant: transport}"
    assert line in io
    (tmp_path / "io_images").mkdir()
    (tmp_path / "io_images" / "transport.yaml").write_text(
        io.replace(line, line[:-1] + f", {policy}}}"), encoding="utf-8")
    return tmp_path / "programs" / "transport.yaml"


class Line:
    """The runner on a virtual clock; every scan's result is kept."""

    def __init__(self, program: Path) -> None:
        self.runner, commands = boot(compile_file(program))
        self.now_ns = 0
        self.results: list[ScanResult] = [self.runner.step(0, commands)]

    @property
    def sim(self) -> SimDriver:
        driver = self.runner.drivers[0]
        assert isinstance(driver, SimDriver)
        return driver

    def run(self, scans: int, command: Command | None = None) -> list[str]:
        events: list[str] = []
        for k in range(scans):
            self.now_ns += PERIOD
            commands = [ProgramCommand(command, id=9)] if command and k == 0 else []
            self.results.append(self.runner.step(self.now_ns, commands))
            events += self.results[-1].events
        return events

    def outputs(self) -> tuple[int, int]:
        image = self.runner.plc.image
        return int(image.qx[0]), int(image.qx[1])


def test_hold_keeps_the_last_inputs_for_n_scans_then_faults_with_safe_outputs(
        tmp_path: Path) -> None:
    line = Line(transport(tmp_path, "on_failure: hold, hold_scans: 4"))
    line.run(400)  # 20 s of production: parts on the belts, motors switching
    while line.outputs() == (0, 0):
        line.run(1)
    line.sim.offline = True
    before = line.runner.inputs.ix[:4].copy()
    events = line.run(4)
    assert line.runner.plc.state is S.RUNNING and events == ["device_down:plant"]
    assert (line.runner.inputs.ix[:4] == before).all()  # the last good inputs, held
    assert line.run(1) == ["device_fault:plant", "plc_fault:device"]
    plc = line.runner.plc
    assert (plc.state, plc.fault_code) == (S.FAULTED, FAULT_DEVICE)
    assert line.outputs() == (0, 0)  # m1, m2 safe: false, in the same scan
    assert plc.fault_reason == "device plant not answering for 5 scans: offline (fault injection)"
    assert line.runner.device_report() == {"plant": {
        "verdict": "fault", "failing_scans": 5, "reason": "offline (fault injection)"}}
    assert line.results[-1].outputs_changed


def test_without_auto_recover_the_plc_waits_for_reset_after_the_device_returns(
        tmp_path: Path) -> None:
    line = Line(transport(tmp_path, "on_failure: fault"))
    line.run(100)
    line.sim.offline = True
    assert line.run(1) == ["device_down:plant", "device_fault:plant", "plc_fault:device"]
    line.run(20)
    line.sim.offline = False
    assert line.run(40) == ["device_ok:plant"]
    assert line.runner.plc.state is S.FAULTED
    assert line.runner.device_report()["plant"]["verdict"] == "ok"
    line.run(1, Command.RESET)
    assert (line.runner.plc.state, line.runner.plc.fault_code) == (S.STOPPED, FAULT_NONE)
    line.run(1, Command.START)
    line.run(100)
    assert line.runner.plc.state is S.RUNNING


def test_auto_recover_continues_production_where_it_stopped(tmp_path: Path) -> None:
    line = Line(transport(tmp_path, "on_failure: hold, hold_scans: 2, auto_recover: true"))
    line.run(600)
    line.sim.offline = True
    line.run(2)
    marking = line.runner.plc.marking()
    line.run(1)
    assert line.runner.plc.state is S.FAULTED
    line.run(10)
    assert line.runner.plc.marking() == marking
    line.sim.offline = False
    assert line.run(1) == ["device_ok:plant", "plc_recovered:device"]
    assert line.runner.plc.state is S.RUNNING
    line.run(2400)  # two more minutes of production
    plant = line.sim.plant.report()
    assert plant.parts_out + plant.in_flight == plant.parts_in > 0


def test_sim_driver_offline_is_down_and_leaves_image_and_plant_alone(tmp_path: Path) -> None:
    line = Line(transport(tmp_path, "on_failure: fault"))
    sim = line.sim
    assert sim.health().value == "ok" and sim.problem() == ""
    sim.offline = True
    assert sim.health().value == "down" and sim.problem() == "offline (fault injection)"
    image = line.runner.inputs.copy()
    image.ix[:] = True
    sim.read_inputs(image, 10**9)
    assert image.ix[:4].all()


# -- the symbols file --------------------------------------------------------------------------

IO = """\
drivers:
  rio:
    kind: modbus
    host: 127.0.0.1
    port: 5020
{policy}
symbols:
  s: {{address: "%IX0.0", channel: "di:0"}}
"""


def io_with(policy: str) -> str:
    return IO.format(policy="\n".join(f"    {line}" for line in policy.splitlines()))


@pytest.mark.parametrize(("policy", "expected"), [
    ("", FaultPolicy()),
    ("on_failure: hold\nhold_scans: 5", FaultPolicy(OnFailure.HOLD, 5)),
    ("on_failure: fault\nauto_recover: true\nstartup_s: 0.5",
     FaultPolicy(OnFailure.FAULT, 0, True, 0.5)),
])
def test_policy_keys_are_read_and_not_passed_to_the_driver(policy: str,
                                                           expected: FaultPolicy) -> None:
    io = parse_io_image(io_with(policy), "io.yaml")
    spec = io.drivers["rio"]
    assert spec.policy == expected
    assert set(spec.params) == {"host", "port"}


@pytest.mark.parametrize(("policy", "expected"), [
    ("on_failure: retry", "io.yaml:6: drivers.rio.on_failure: on_failure 'retry': "
                          "expected fault or hold"),
    ("on_failure: hold", "io.yaml:6: drivers.rio.on_failure: on_failure: hold needs "
                         "hold_scans: N (scans to hold the last inputs)"),
    ("on_failure: hold\nhold_scans: 0", "io.yaml:7: drivers.rio.hold_scans: hold_scans must be "
                                        "an integer >= 1, got 0"),
    ("hold_scans: 3", "io.yaml:6: drivers.rio.hold_scans: hold_scans needs on_failure: hold "
                      "(fault faults at once)"),
    ("auto_recover: yes", "io.yaml:6: drivers.rio.auto_recover: auto_recover must be true or "
                          "false ('yes' is text here, not a boolean: write true or false)"),
    ("startup_s: -1", "io.yaml:6: drivers.rio.startup_s: startup_s must be a number of "
                      "seconds >= 0, got -1"),
])
def test_bad_policy_keys_are_located_problems(policy: str, expected: str) -> None:
    with pytest.raises(ProgramError) as info:
        parse_io_image(io_with(policy), "io.yaml")
    assert [str(p) for p in info.value.problems] == [expected]


def test_the_example_in_docs_faults_md_is_a_valid_symbols_file() -> None:
    text = (REPO / "docs" / "faults.md").read_text(encoding="utf-8")
    example = text.split("```yaml\n", 1)[1].split("```", 1)[0]
    io = parse_io_image(example, "faults.md")
    assert io.drivers["rio"].policy == FaultPolicy(OnFailure.HOLD, 5, False, 5.0)
