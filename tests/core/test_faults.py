"""Device fault policy in the pure core: one answering/not-answering observation per scan.

No driver, socket or clock: the device's answer is a bool and time a plain now_ns. The
runtime feeds the same monitor from the drivers' health (tests/runtime/test_fault_policy.py).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from softplc.core.faults import DeviceMonitor, Verdict
from softplc.core.lifecycle import Command, PlcState
from softplc.core.net import CompiledNet
from softplc.core.plc import FAULT_DEVICE, FAULT_NONE, FAULT_WATCHDOG, ProgramCommand
from softplc.core.symbols import FaultPolicy, OnFailure
from tests.core.helpers import Bench, compile_program

S = PlcState
MS = 1_000_000
PERIOD = 10 * MS

# `q` (safe true) and `r` (safe false) are on while `on` is marked; `tick` counts every 50 ms.
BODY = """
places:
  on: {tokens: 1, outputs: [q]}
  ticks: {}
transitions:
  tick:
    from: [on]
    to: [on, ticks]
    delay: 50ms
    do: [r = 1]
"""


@pytest.fixture(scope="module")
def net(tmp_path_factory: pytest.TempPathFactory) -> CompiledNet:
    return compile_program(Path(tmp_path_factory.mktemp("faults")), BODY)


def hold(n: int, auto: bool = False) -> FaultPolicy:
    return FaultPolicy(OnFailure.HOLD, n, auto, startup_s=0)


FAULT_AT_ONCE = FaultPolicy(startup_s=0)


class Rig:
    """A bench PLC with a monitor: `scan(rio=False)` is one scan in which rio did not answer."""

    def __init__(self, net: CompiledNet, **policies: FaultPolicy) -> None:
        self.bench = Bench(net)
        self.monitor = DeviceMonitor()
        self.policies = policies
        self.now_ns = 0
        self.events: list[str] = []
        self.answers = dict.fromkeys(policies, True)

    @property
    def plc(self):  # type: ignore[no-untyped-def]
        return self.bench.plc

    def scan(self, commands: list[ProgramCommand] | None = None, **answers: bool) -> list[str]:
        self.answers.update(answers)
        self.now_ns += PERIOD
        why = lambda name: f"{name} is silent"  # noqa: E731
        events = self.monitor.before_scan(self.plc, self.answers, self.policies, why, self.now_ns)
        result = self.bench.scan(self.now_ns, commands or [])
        events += list(result.events) + self.monitor.after_scan(self.plc, self.now_ns)
        self.events += events
        return events

    def outputs(self) -> tuple[int, int]:
        return self.bench.get("q"), self.bench.get("r")


def cmd(command: Command) -> list[ProgramCommand]:
    return [ProgramCommand(command)]


def test_fault_at_once_faults_in_the_first_silent_scan_with_safe_outputs(net: CompiledNet) -> None:
    rig = Rig(net, rio=FAULT_AT_ONCE)
    for _ in range(10):
        rig.scan()
    assert rig.plc.state is S.RUNNING and rig.outputs() == (1, 1)
    events = rig.scan(rio=False)
    assert events == ["device_down:rio", "device_fault:rio", "plc_fault:device"]
    assert (rig.plc.state, rig.plc.fault_code) == (S.FAULTED, FAULT_DEVICE)
    assert rig.outputs() == (1, 0)  # the declared safe values: q safe true, r safe false
    assert rig.plc.fault_reason == "device rio not answering for 1 scans: rio is silent"
    assert rig.monitor.report()["rio"] == {"verdict": "fault", "failing_scans": 1,
                                           "reason": "rio is silent"}


def test_hold_keeps_running_for_n_silent_scans_then_faults(net: CompiledNet) -> None:
    rig = Rig(net, rio=hold(3))
    rig.scan()
    states = []
    for _ in range(5):
        rig.scan(rio=False)
        states.append(rig.plc.state)
    assert states == [S.RUNNING] * 3 + [S.FAULTED] * 2
    assert rig.events == ["device_down:rio", "device_fault:rio", "plc_fault:device"]
    assert rig.monitor.watches["rio"].failing_scans == 5


def test_a_device_back_within_the_hold_resets_the_count(net: CompiledNet) -> None:
    rig = Rig(net, rio=hold(2))
    for answer in [False, False, True, False, False, True, False, False]:
        rig.scan(rio=answer)
    assert rig.plc.state is S.RUNNING
    assert rig.events.count("device_down:rio") == 3 and rig.events.count("device_ok:rio") == 2
    rig.scan(rio=False)
    assert rig.plc.state is S.FAULTED


def test_a_booting_device_is_not_failing_until_startup_s(net: CompiledNet) -> None:
    rig = Rig(net, rio=FaultPolicy(startup_s=0.1))
    for _ in range(10):  # 90 ms since the first scan saw it: still booting
        rig.scan(rio=False)
    assert rig.plc.state is S.RUNNING and rig.monitor.watches["rio"].verdict is Verdict.STARTING
    rig.scan(rio=False)
    assert rig.plc.state is S.FAULTED


def test_a_device_that_answered_once_gets_no_startup_grace_again(net: CompiledNet) -> None:
    rig = Rig(net, rio=FaultPolicy(startup_s=10.0))
    rig.scan(rio=True)
    rig.scan(rio=False)
    assert rig.plc.state is S.FAULTED


def test_recovery_needs_reset_without_auto_recover(net: CompiledNet) -> None:
    rig = Rig(net, rio=FAULT_AT_ONCE)
    for _ in range(12):
        rig.scan()
    assert rig.plc.marking()["ticks"] >= 1
    rig.scan(rio=False)
    rig.scan(rio=False)
    assert rig.scan(rio=True) == ["device_ok:rio"]
    for _ in range(5):
        rig.scan()
    assert (rig.plc.state, rig.plc.fault_code) == (S.FAULTED, FAULT_DEVICE)
    # The lifecycle table (docs/design.md section 4): FAULTED rejects resume; reset is the way out.
    rig.scan(cmd(Command.RESUME))
    assert rig.bench.last.replies[0].ok is False and rig.plc.state is S.FAULTED
    rig.scan(cmd(Command.RESET))
    assert (rig.plc.state, rig.plc.fault_code, rig.plc.fault_reason) == (S.STOPPED, FAULT_NONE, "")
    assert rig.plc.marking().get("ticks", 0) == 0
    rig.scan(cmd(Command.START))
    assert rig.plc.state is S.RUNNING and rig.outputs()[0] == 1


def test_reset_while_the_device_is_still_silent_faults_again_on_start(net: CompiledNet) -> None:
    rig = Rig(net, rio=FAULT_AT_ONCE)
    rig.scan(rio=False)
    rig.scan(cmd(Command.RESET))
    assert rig.plc.state is S.STOPPED  # stopped: outputs are safe anyway, no fault
    rig.scan()
    assert rig.plc.state is S.STOPPED
    events = rig.scan(cmd(Command.START))
    assert rig.plc.state is S.FAULTED and "plc_fault:device" in events
    assert rig.outputs() == (1, 0)  # the start scan's outputs never reach the device


def test_auto_recover_resumes_with_marking_outputs_and_timers_kept(net: CompiledNet) -> None:
    rig = Rig(net, rio=hold(1, auto=True))
    for _ in range(12):  # ticks at 50 and 100 ms (re-enabled at 110), the third due at 160
        rig.scan()
    ticks = rig.plc.marking()["ticks"]
    assert ticks == 2 and rig.outputs() == (1, 1)
    rig.scan(rio=False)
    for _ in range(20):  # 200 ms faulted: frozen timers must not tick
        rig.scan(rio=False)
    assert rig.plc.state is S.FAULTED and rig.outputs() == (1, 0)
    events = rig.scan(rio=True)
    assert events == ["device_ok:rio", "plc_recovered:device"]
    assert (rig.plc.state, rig.plc.fault_code, rig.plc.fault_reason) == (S.RUNNING, FAULT_NONE, "")
    assert rig.outputs() == (1, 1) and rig.plc.marking()["ticks"] == ticks
    for _ in range(2):  # faulted at 130 with 30 ms left: they run from the recovery on
        rig.scan()
    assert rig.plc.marking()["ticks"] == ticks
    rig.scan()
    rig.scan()
    assert rig.plc.marking()["ticks"] == ticks + 1


def test_auto_recover_waits_for_every_failed_device(net: CompiledNet) -> None:
    rig = Rig(net, rio=FaultPolicy(auto_recover=True, startup_s=0),
              aux=FaultPolicy(auto_recover=True, startup_s=0))
    rig.scan(rio=False, aux=False)
    rig.scan(rio=True)
    assert rig.plc.state is S.FAULTED
    rig.scan(aux=True)
    assert rig.plc.state is S.RUNNING


def test_auto_recover_needs_every_culprit_to_allow_it(net: CompiledNet) -> None:
    rig = Rig(net, rio=FaultPolicy(auto_recover=True, startup_s=0), aux=FAULT_AT_ONCE)
    rig.scan(rio=False, aux=False)
    rig.scan(rio=True, aux=True)
    rig.scan()
    assert rig.plc.state is S.FAULTED


def test_watchdog_faults_are_never_auto_recovered(net: CompiledNet) -> None:
    rig = Rig(net, rio=FaultPolicy(auto_recover=True, startup_s=0))
    rig.scan()
    rig.plc.fault(FAULT_WATCHDOG)
    rig.scan(rio=False)
    rig.scan(rio=True)
    assert (rig.plc.state, rig.plc.fault_code) == (S.FAULTED, FAULT_WATCHDOG)


def test_a_device_failing_while_stopped_does_not_fault_the_plc(net: CompiledNet) -> None:
    rig = Rig(net, rio=FAULT_AT_ONCE)
    rig.scan(cmd(Command.STOP))
    events = rig.scan(rio=False)
    assert rig.plc.state is S.STOPPED and events == ["device_down:rio", "device_fault:rio"]
    assert rig.scan(rio=True) == ["device_ok:rio"]
    rig.scan(cmd(Command.RESUME))
    assert rig.plc.state is S.RUNNING


@given(answers=st.lists(st.booleans(), max_size=40), held=st.integers(0, 4), auto=st.booleans())
def test_faulted_exactly_when_a_silence_outlasts_the_hold(
        tmp_path_factory: pytest.TempPathFactory, answers: list[bool], held: int,
        auto: bool) -> None:
    net = _shared_net(tmp_path_factory)
    policy = hold(held, auto) if held else FaultPolicy(OnFailure.FAULT, 0, auto, startup_s=0)
    rig = Rig(net, rio=policy)
    run, ever = 0, False
    for answer in answers:
        rig.scan(rio=answer)
        run = 0 if answer else run + 1
        ever = ever or run > held
        faulted = run > held if auto else ever
        assert (rig.plc.state is S.FAULTED) == faulted
        assert rig.plc.fault_code == (FAULT_DEVICE if faulted else FAULT_NONE)


_NETS: dict[str, CompiledNet] = {}


def _shared_net(factory: pytest.TempPathFactory) -> CompiledNet:
    if "net" not in _NETS:
        _NETS["net"] = compile_program(Path(factory.mktemp("prop")), BODY)
    return _NETS["net"]
