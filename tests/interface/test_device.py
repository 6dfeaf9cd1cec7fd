"""The device interface of the seed paper (Fig. 2) on the simulated plants, in virtual time:
variable handling, program handling and events, Python style and the paper's 0/-1 facade.
No sockets, no sleeps."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from softplc.core.events import EventMemory, evaluate
from softplc.core.image import ProcessImage, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.problems import ProgramError
from softplc.core.symbols import DIRECTION_OF_AREA, EventKind, EventSpec, Symbol, SymType
from softplc.devices.driver import Health
from softplc.devices.sim import SimDriver
from softplc.interface import (
    DeviceError,
    DeviceInterface,
    DeviceUnavailable,
    Notification,
    ProgramHandlingError,
    UnknownAddress,
    UnknownEvent,
    WrongDirection,
    WrongType,
    open_device,
)
from softplc.program.io_image import load_io_image

ROOT = Path(__file__).resolve().parents[2]
S = 1_000_000_000
PERIOD = 10_000_000
TRANSPORT_IO = "io_images/transport.yaml"
TRANSPORT = "programs/transport.yaml"


@pytest.fixture(autouse=True)
def _repo_root(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(ROOT)  # the paper's calls use paths relative to the project


@pytest.fixture
def dev() -> Iterator[DeviceInterface]:
    with open_device(TRANSPORT_IO) as device:
        yield device


@pytest.fixture
def running(dev: DeviceInterface) -> DeviceInterface:
    assert dev.download(TRANSPORT, None) == 0
    assert dev.start("transport") == 0
    dev.step()
    return dev


def plant_of(dev: DeviceInterface) -> SimDriver:
    (driver,) = dev.drivers
    assert isinstance(driver, SimDriver)
    return driver


def write_text(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


# -- variable handling -------------------------------------------------------------------------


def test_reads_see_the_last_scan_zero_before_the_first(dev: DeviceInterface) -> None:
    assert dev.readDB("s1_i") is False
    dev.run_for(S + PERIOD)  # the first part is placed in front of s1_i at t = 1 s
    assert dev.readDB("s1_i") is True
    assert dev.readDB("%IX0.0") is True and dev.readDB("I0.0") is True
    assert dev.read("s1_i") == 1
    sensors = plant_of(dev).plant.read_sensors()
    assert {name: int(bool(dev.readDB(name))) for name in sensors} == sensors


@pytest.mark.parametrize("address", ["nope", "%IX0.9", "%QX", "Z1.2", "%IX100.0", "%MW1024", ""])
def test_readDB_of_an_unknown_address_is_none(dev: DeviceInterface, address: str) -> None:
    assert dev.readDB(address) is None
    assert dev.last_error
    with pytest.raises(UnknownAddress):
        dev.read(address)


def test_readDB_of_a_word_and_readAnalog_of_a_bit_are_none(dev: DeviceInterface) -> None:
    assert dev.readDB("%QW0") is None and dev.readDB("parts_delivered") is None
    assert dev.readAnalog("m1") is None and dev.readAnalog("%IX0.0") is None
    with pytest.raises(WrongType):
        dev.read_analog("s1_i")
    assert dev.readDB("m1") is False and dev.last_error == ""


def test_writeDB_to_memory_applies_at_the_next_scan(dev: DeviceInterface) -> None:
    assert dev.writeDB("hold", 1) == 0
    assert dev.writeDB("M1.7", True) == 0
    assert dev.readDB("hold") is False  # journaled, not yet applied
    dev.step()
    assert dev.readDB("hold") is True and dev.readDB("%MX0.0") is True
    assert dev.readDB("%MX1.7") is True
    assert dev.writeDB("%MX0.0", 0) == 0
    dev.step()
    assert dev.readDB("hold") is False


def test_writeAnalog_and_readAnalog_round_trip(dev: DeviceInterface) -> None:
    assert dev.writeAnalog("%MW5", 65535) == 0
    assert dev.writeAnalog("MW6", 0) == 0
    assert dev.readAnalog("%MW5") == 0
    dev.step()
    assert dev.readAnalog("%MW5") == 65535 and dev.readAnalog("MW5") == 65535
    assert dev.read("%MW5") == 65535


# (paper function, address, value, error the Python-style write/write_analog raises)
BAD_WRITES: list[tuple[str, str, object, type[DeviceError] | None]] = [
    ("writeDB", "s1_i", 1, WrongDirection),
    ("writeDB", "%IX0.3", 0, WrongDirection),
    ("writeDB", "I0.1", 1, WrongDirection),
    ("writeDB", "hold", 2, WrongType),
    ("writeDB", "m1", -1, WrongType),
    ("writeDB", "m1", 0.5, WrongType),
    ("writeDB", "m1", "1", WrongType),
    ("writeDB", "parts_delivered", 1, None),  # a word through the bit function; write() takes it
    ("writeDB", "nope", 1, UnknownAddress),
    ("writeDB", "%QX100.0", 1, UnknownAddress),
    ("writeAnalog", "%MW0", 65536, WrongType),
    ("writeAnalog", "%MW0", -1, WrongType),
    ("writeAnalog", "%MW0", True, WrongType),
    ("writeAnalog", "m1", 1, WrongType),  # a bit through the word function
    ("writeAnalog", "%IW0", 1, WrongDirection),
    ("writeAnalog", "%QW1024", 1, UnknownAddress),
]


@pytest.mark.parametrize(("function", "address", "value", "error"), BAD_WRITES)
def test_a_bad_write_returns_minus_one_and_changes_nothing(
        dev: DeviceInterface, function: str, address: str, value: object,
        error: type[DeviceError] | None) -> None:
    dev.run_for(2 * S)
    before = dev.snapshot()
    assert getattr(dev, function)(address, value) == -1
    assert dev.last_error
    assert dev.snapshot().equals(before)
    if error is not None:
        python_style = dev.write if function == "writeDB" else dev.write_analog
        with pytest.raises(error):
            python_style(address, value)  # type: ignore[arg-type]
    dev.step()  # nothing was journaled: the scan changes only what the plant changes
    after = dev.snapshot()
    for name in ("qx", "qw", "mx", "mw"):
        assert (getattr(after, name) == getattr(before, name)).all()


def test_a_write_to_an_output_the_program_does_not_hold_sticks(running: DeviceInterface) -> None:
    assert running.writeAnalog("parts_delivered", 7) == 0  # written only when take_off fires
    running.step()
    assert running.readAnalog("parts_delivered") == 7


def test_a_program_overwrites_an_output_it_drives(running: DeviceInterface) -> None:
    assert running.writeDB("m2", 1) == 0  # c2.idle is marked: the program drives m2 off
    running.step()  # the write is applied at this scan's start and overwritten in it
    assert running.readDB("m2") is False


def test_outputs_are_safe_while_no_program_runs(dev: DeviceInterface) -> None:
    assert dev.writeDB("m2", 1) == 0
    dev.step()
    assert dev.readDB("m2") is False


# -- program handling --------------------------------------------------------------------------


@pytest.mark.parametrize("command", ["start", "stop", "reset", "resume", "kill"])
def test_every_command_but_download_is_refused_when_empty(dev: DeviceInterface,
                                                           command: str) -> None:
    assert getattr(dev, command)("transport") == -1
    assert "EMPTY" in dev.last_error and command in dev.last_error
    assert dev.state is PlcState.EMPTY
    with pytest.raises(ProgramHandlingError, match="EMPTY"):
        getattr(dev, f"{command}_program")()
    assert dev.commands == [(command, "transport"), (command, "")]


LIFECYCLE: list[tuple[str, int, PlcState]] = [
    ("download", 0, PlcState.STOPPED),
    ("stop", -1, PlcState.STOPPED),
    ("start", 0, PlcState.RUNNING),
    ("start", -1, PlcState.RUNNING),
    ("resume", -1, PlcState.RUNNING),
    ("reset", -1, PlcState.RUNNING),
    ("stop", 0, PlcState.STOPPED),
    ("resume", 0, PlcState.RUNNING),
    ("stop", 0, PlcState.STOPPED),
    ("reset", 0, PlcState.STOPPED),
    ("kill", 0, PlcState.KILLED),
    ("start", -1, PlcState.KILLED),
    ("kill", -1, PlcState.KILLED),
    ("reset", 0, PlcState.STOPPED),
    ("start", 0, PlcState.RUNNING),
    ("kill", 0, PlcState.KILLED),
    ("download", 0, PlcState.STOPPED),
]


def test_the_paper_commands_follow_the_lifecycle(dev: DeviceInterface) -> None:
    for command, code, state in LIFECYCLE:
        args = (TRANSPORT, None) if command == "download" else ("transport",)
        assert getattr(dev, command)(*args) == code, (command, dev.last_error)
        assert dev.state is state, command
        dev.step()
    assert [c for c, _ in dev.commands] == [c for c, _, _ in LIFECYCLE]


def test_stop_holds_the_marking_and_resume_continues(running: DeviceInterface) -> None:
    running.run_for(3 * S)
    marking = running.marking()
    assert running.stop() == 0
    running.run_for(5 * S)
    assert running.marking() == marking
    assert running.readDB("m1") is False  # safe while stopped
    assert running.resume() == 0
    running.step()
    assert running.marking() == marking and running.readDB("m1") is True


def test_download_with_a_location(dev: DeviceInterface) -> None:
    assert dev.download("transport.yaml", "programs") == 0
    assert dev.program is not None and dev.program.name == "transport"
    assert dev.start("transport.yaml") == 0  # the file given to download names it too
    assert dev.commands == [("download", "programs/transport.yaml"), ("start", "transport.yaml")]


def test_a_command_for_another_program_is_refused(running: DeviceInterface) -> None:
    assert running.stop("drilling") == -1
    assert "transport" in running.last_error
    assert running.state is PlcState.RUNNING


BROKEN = """\
program: broken
io_image: {io}
places:
  idle: {{tokens: 1}}
transitions:
  go:
    from: [idle, nowhere]
    to: [idle]
    when: no_such_sensor
"""


def test_a_bad_download_returns_minus_one_and_the_running_program_goes_on(
        running: DeviceInterface, tmp_path: Path) -> None:
    bad = write_text(tmp_path / "broken.yaml", BROKEN.format(io=ROOT / TRANSPORT_IO))
    running.run_for(2 * S)
    net, marking = running.program, running.marking()
    assert running.download(str(bad), None) == -1
    assert "nowhere" in running.last_error and "no_such_sensor" in running.last_error
    assert running.download("programs/missing.yaml", None) == -1
    assert running.state is PlcState.RUNNING
    assert running.program is net and running.marking() == marking
    with pytest.raises(ProgramHandlingError) as info:
        running.download_program(bad)
    assert isinstance(info.value.__cause__, ProgramError)
    assert len(info.value.__cause__.problems) >= 2
    running.run_for(2 * S)
    assert running.state is PlcState.RUNNING and running.program is net


def test_download_while_running_needs_online_change(running: DeviceInterface) -> None:
    net = running.program
    assert running.download(TRANSPORT, None) == -1
    assert "RUNNING" in running.last_error and "download" in running.last_error
    assert running.program is net
    summary = running.download_program(TRANSPORT, online=True)
    assert summary.name == "transport" and running.state is PlcState.RUNNING


def test_a_program_for_other_symbols_is_refused(dev: DeviceInterface) -> None:
    assert dev.download("programs/drilling.yaml", None) == -1
    assert "io_images/drilling.yaml" in dev.last_error
    assert dev.state is PlcState.EMPTY and dev.program is None


def test_kill_drops_pending_writes(running: DeviceInterface) -> None:
    assert running.writeDB("hold", 1) == 0
    assert running.kill("transport") == 0
    running.step()
    assert running.readDB("hold") is False
    assert running.readDB("m1") is False and running.readDB("m2") is False


# -- closed loop -------------------------------------------------------------------------------


@dataclass
class Run:
    dev: DeviceInterface
    s2_o: list[bool]  # per scan
    m2: list[bool]
    notes: list[Notification]


@pytest.fixture(scope="module")
def transport_run() -> Iterator[Run]:
    """Two minutes of the transport program on its plant, one readDB per scan."""
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ROOT)
        dev = open_device(TRANSPORT_IO, seed=3)
        assert dev.download(TRANSPORT, None) == 0
        assert dev.subscribeEvent("part_at_output") == 0
        assert dev.subscribeEvent("m2") == 0
        assert dev.start("transport") == 0
        s2_o, m2, notes = [], [], []
        for k in range(120 * S // PERIOD):
            dev.step(PERIOD)
            s2_o.append(bool(dev.readDB("s2_o")))
            m2.append(bool(dev.readDB("m2")))
            if k % 1000 == 999:
                notes += dev.notifyEvent()
        notes += dev.notifyEvent()
        yield Run(dev, s2_o, m2, notes)
        dev.close()


def test_the_transport_program_moves_parts(transport_run: Run) -> None:
    dev = transport_run.dev
    report = plant_of(dev).plant.report()
    assert report.faults == ()
    assert report.parts_out >= 5
    assert dev.readAnalog("parts_delivered") == report.parts_out
    assert dev.state is PlcState.RUNNING
    assert dev.health() == {"plant": Health.OK}
    assert dev.commands == [("download", TRANSPORT), ("start", "transport")]


def test_readDB_agrees_with_the_image_and_the_plant(transport_run: Run) -> None:
    dev = transport_run.dev
    image = dev.snapshot()
    for name in ("s1_i", "s1_o", "s2_i", "s2_o", "m1", "m2", "hold"):
        sym = dev.io.symbols[name]
        assert dev.readDB(name) is bool(image.get(sym.address))
        assert dev.readDB(str(sym.address)) is dev.readDB(name)
    sensors = plant_of(dev).plant.read_sensors()
    assert {name: int(bool(dev.readDB(name))) for name in sensors} == sensors


def edges(values: Sequence[bool], rising_only: bool) -> list[int]:
    """Scan numbers at which the value rose (or changed), the first scan only recording."""
    return [k for k in range(1, len(values))
            if values[k] != values[k - 1] and (values[k] or not rising_only)]


def test_each_occurrence_is_notified_once_in_order(transport_run: Run) -> None:
    notes = transport_run.notes
    at_output = [n.scan for n in notes if n.event == "part_at_output"]
    motor = [n.scan for n in notes if n.event == "m2"]
    assert at_output == edges(transport_run.s2_o, rising_only=True)
    assert motor == edges(transport_run.m2, rising_only=False)
    assert len(at_output) >= 5
    assert [n.scan for n in notes] == sorted(n.scan for n in notes)
    assert all(n.time_ns == n.scan * PERIOD for n in notes)
    assert transport_run.dev.notifyEvent() == []


def test_deleteEvent_stops_notifications(running: DeviceInterface) -> None:
    assert running.subscribeEvent("part_at_output") == 0
    while not (notes := running.notifyEvent()):
        running.step()
    assert [n.event for n in notes] == ["part_at_output"]
    assert running.deleteEvent("part_at_output") == 0
    s2_o = [bool(running.readDB("s2_o"))]
    for _ in range(60 * S // PERIOD):
        running.step()
        s2_o.append(bool(running.readDB("s2_o")))
    assert edges(s2_o, rising_only=True)  # the condition occurred again ...
    assert running.notifyEvent() == []  # ... unsubscribed
    assert running.deleteEvent("part_at_output") == -1 and "not subscribed" in running.last_error


def test_a_change_right_after_subscribing_is_notified(dev: DeviceInterface) -> None:
    dev.step()
    assert dev.writeDB("hold", 1) == 0
    assert dev.subscribeEvent("hold") == 0
    dev.step()
    assert [(n.scan, n.event) for n in dev.notifyEvent()] == [(1, "hold")]


def test_a_resubscription_does_not_report_the_past(dev: DeviceInterface) -> None:
    assert dev.subscribeEvent("hold") == 0
    dev.step()
    assert dev.deleteEvent("hold") == 0
    assert dev.writeDB("hold", 1) == 0
    dev.step()
    assert dev.subscribeEvent("hold") == 0
    dev.step()
    assert dev.notifyEvent() == []
    assert dev.writeDB("hold", 0) == 0
    dev.step()
    assert [n.event for n in dev.notifyEvent()] == ["hold"]


@pytest.mark.parametrize("name", ["nope", "%IX0.0", "", "part_delivered"])
def test_subscribing_an_unknown_event_fails(dev: DeviceInterface, name: str) -> None:
    assert dev.subscribeEvent(name) == -1
    assert dev.deleteEvent(name) == -1
    with pytest.raises(UnknownEvent):
        dev.subscribe_event(name)


# -- threshold with hysteresis -----------------------------------------------------------------

THERMO_IO = """\
symbols:
  temp: {address: "%IW0", type: word}
events:
  over_temp: {above: temp, threshold: 80, hysteresis: 5}
  too_cold:  {below: temp, threshold: 10, hysteresis: 2}
"""


class ScriptedInputs:
    """A test driver: one value of %IW0 per scan, from a script."""

    name = "script"

    def __init__(self, values: Sequence[int]) -> None:
        self.values = iter(values)

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        image.iw[0] = next(self.values)

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        pass

    def health(self) -> Health:
        return Health.OK


#        0   1   2   3   4   5   6   7   8   9  10 11  12  13
SCRIPT = [50, 79, 81, 79, 90, 76, 75, 81, 81, 20, 9, 11, 12, 5]


def test_threshold_events_with_hysteresis_through_the_device(tmp_path: Path) -> None:
    io = load_io_image(write_text(tmp_path / "thermo.yaml", THERMO_IO))
    dev = DeviceInterface(io, [ScriptedInputs(SCRIPT)])
    assert dev.subscribeEvent("over_temp") == 0 and dev.subscribeEvent("too_cold") == 0
    dev.run_for(len(SCRIPT) * PERIOD)
    assert [(n.scan, n.event) for n in dev.notifyEvent()] == [
        (2, "over_temp"), (7, "over_temp"), (10, "too_cold"), (13, "too_cold")]
    assert dev.readAnalog("temp") == 5
    assert dev.writeAnalog("temp", 1) == -1  # an input: the driver's


def test_a_device_without_drivers_opens(tmp_path: Path) -> None:
    with open_device(write_text(tmp_path / "thermo.yaml", THERMO_IO)) as dev:
        assert dev.drivers == () and dev.step().outputs.iw[0] == 0


@pytest.mark.parametrize(("kind", "values", "expected"), [
    (EventKind.ABOVE, [50, 81, 79, 90, 75, 81], [1, 5]),
    (EventKind.BELOW, [50, 9, 14, 5, 15, 9], [1, 5]),
    (EventKind.RISING, [0, 1, 1, 0, 1], [1, 4]),
    (EventKind.FALLING, [1, 0, 0, 1, 0], [1, 4]),
    (EventKind.CHANGE, [3, 3, 4, 4, 3], [2, 4]),
])
def test_event_conditions_on_scripted_images(kind: EventKind, values: list[int],
                                             expected: list[int]) -> None:
    threshold = {EventKind.ABOVE: 80, EventKind.BELOW: 10}.get(kind, 0)
    spec = EventSpec("e", kind, "x", threshold=threshold, hysteresis=5)
    address = parse_address("%IW0")
    symbols = {"x": Symbol("x", address, SymType.WORD, DIRECTION_OF_AREA[address.area])}
    image, memory = ProcessImage(), EventMemory()
    seen = []
    for k, value in enumerate(values):
        image.iw[0] = value
        if evaluate([spec], symbols, image, memory):
            seen.append(k)
    assert seen == expected


# -- reconfiguration and closing ---------------------------------------------------------------


def test_the_same_interface_runs_the_drilling_cell() -> None:
    with open_device("io_images/drilling.yaml", seed=1) as dev:
        assert type(dev) is DeviceInterface
        assert dev.download("programs/transport.yaml", None) == -1
        assert dev.download("drilling.yaml", "programs") == 0
        assert dev.subscribeEvent("part_loaded") == 0
        assert dev.start("drilling") == 0
        dev.run_for(60 * S)
        report = plant_of(dev).plant.report()
        assert report.faults == () and report.parts_drilled >= 3
        assert dev.readAnalog("parts_drilled") == report.parts_drilled
        loaded = [n for n in dev.notifyEvent() if n.event == "part_loaded"]
        assert len(loaded) >= report.parts_drilled
        assert dev.stop("drilling") == 0 and dev.state is PlcState.STOPPED


def test_a_closed_device_answers_with_errors(dev: DeviceInterface) -> None:
    dev.close()
    dev.close()
    assert dev.readDB("m1") is None and dev.readAnalog("%QW0") is None
    assert dev.writeDB("hold", 1) == -1 and dev.writeAnalog("%MW0", 1) == -1
    assert dev.download(TRANSPORT, None) == -1 and dev.start() == -1
    assert dev.subscribeEvent("m1") == -1
    assert "closed" in dev.last_error
    with pytest.raises(DeviceUnavailable):
        dev.step()
    assert plant_of(dev).health() is Health.DOWN


@pytest.mark.parametrize("opener", [
    lambda: open_device("io_images/missing.yaml"),
    lambda: open_device(ROOT / "programs/transport.yaml"),  # a program, not an io image
])
def test_open_device_reports_a_bad_io_image(opener: Callable[[], DeviceInterface]) -> None:
    with pytest.raises(DeviceError):
        opener()


def test_time_only_moves_with_steps(dev: DeviceInterface) -> None:
    assert dev.now_ns == 0
    dev.step()
    dev.step(5 * PERIOD)
    assert dev.now_ns == 6 * PERIOD
    assert dev.run_for(S - 1, PERIOD) == 99 and dev.now_ns == 105 * PERIOD
    with pytest.raises(ValueError):
        dev.step(0)
