"""go_safe, close and the heartbeat against a real pymodbus 3.16 remote-I/O module on 127.0.0.1
(tests/devices/remote_io_device.py, with its own communication watchdog).

A confirmed go_safe means the device already holds the safe values when the call returns: the
tests read the coil right after, without waiting. Every wait is bounded by a deadline."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from types import MappingProxyType
from typing import Any

import pytest

from softplc.core.image import ProcessImage
from softplc.core.symbols import DriverSpec, Symbol
from softplc.devices.driver import DeviceError, Health, go_safe_all
from softplc.devices.modbus_io import ModbusIoDriver
from softplc.program.io_image import load_io_image
from softplc.runtime.runner import open_drivers
from tests.devices.remote_io_device import FC_HR, RemoteIoDevice
from tests.devices.test_modbus_io import DRIVER, Scanner, sym
from tests.support import free_port, wait_until

ROOT = Path(__file__).resolve().parents[2]
LAMP = "coil:0"


def spec(port: int, name: str = DRIVER, **params: Any) -> DriverSpec:
    base: dict[str, Any] = {"host": "127.0.0.1", "port": port, "timeout_s": 0.1,
                            "reconnect_min_s": 0.05, "reconnect_max_s": 0.2}
    base.update(params)
    return DriverSpec(name, "modbus", MappingProxyType(base))


def lamp(driver: str = DRIVER) -> list[Symbol]:
    return [sym("lamp", "%QX0.0", LAMP, driver=driver), sym("part", "%IX0.0", "di:0", driver)]


@pytest.fixture
def device() -> Iterator[RemoteIoDevice]:
    dev = RemoteIoDevice().start()
    yield dev
    dev.dispose()


@pytest.fixture
def make_driver() -> Iterator[Callable[..., ModbusIoDriver]]:
    made: list[ModbusIoDriver] = []

    def make(driver_spec: DriverSpec, symbols: list[Symbol] | None = None) -> ModbusIoDriver:
        drv = ModbusIoDriver(driver_spec, lamp(driver_spec.name) if symbols is None else symbols)
        made.append(drv)
        drv.open()
        return drv

    yield make
    for drv in made:
        drv.close()


def lamp_on(device: RemoteIoDevice, drv: ModbusIoDriver) -> Scanner:
    """Scan with the lamp commanded on until the device has it on."""
    plc = Scanner(drv)
    plc.image.qx[0] = True
    assert plc.until(lambda: device.coil(0), timeout_s=3.0)
    return plc


def safe_image(plc: Scanner) -> ProcessImage:
    plc.image.qx[0] = False
    return plc.image


# ----- go_safe -----


def test_go_safe_returns_once_the_device_holds_the_safe_values(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    drv = make_driver(spec(device.port))
    plc = lamp_on(device, drv)
    for _ in range(5):
        plc.image.qx[0] = True
        drv.write_outputs(plc.image, plc.now_ns)  # queued, maybe not yet sent
        t0 = time.monotonic()
        assert drv.go_safe(safe_image(plc), 1.0)
        assert time.monotonic() - t0 < 1.0
        assert not device.coil(0)  # at once: confirmed means written
        assert drv.problem() == ""
    time.sleep(0.2)  # the queued lamp-on was replaced, never sent after the safe write
    assert not device.coil(0)


def test_go_safe_cuts_a_reconnect_backoff_short(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    backoff_s = 20.0  # far longer than the test: a reconnect within it is go_safe's doing
    drv = make_driver(spec(device.port, reconnect_min_s=backoff_s, reconnect_max_s=backoff_s))
    plc = lamp_on(device, drv)
    device.stop()
    assert plc.until(lambda: drv.stats().consecutive_failures >= 1, timeout_s=3.0)
    failed = time.monotonic()
    device.start()  # the driver now sleeps at least backoff_s before its next connect attempt
    device.set(1, 0, [True])  # the restarted module comes back with the lamp on
    assert drv.go_safe(safe_image(plc), 1.0)
    assert not device.coil(0)
    # The I/O thread itself reconnected, before its backoff would have ended.
    assert wait_until(lambda: drv.stats().connected, timeout_s=5.0, step_s=0.002)
    assert time.monotonic() - failed < backoff_s


def test_go_safe_with_a_wedged_io_thread_writes_on_a_fresh_connection(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    drv = make_driver(spec(device.port))
    plc = lamp_on(device, drv)
    assert drv._loop is not None
    wedge, wedged = threading.Event(), threading.Event()

    def stuck() -> None:  # the I/O thread's loop is stuck until the test lets it go
        wedged.set()
        wedge.wait(30)

    drv._loop.call_soon_threadsafe(stuck)
    assert wedged.wait(5)
    plc.image.qx[0] = True
    drv.write_outputs(plc.image, plc.now_ns)  # lamp-on queued behind the wedge
    assert drv.go_safe(safe_image(plc), 0.6)
    assert not device.coil(0) and not wedge.is_set()  # written while the thread was stuck
    wedge.set()  # the thread comes back: it must not send the stale lamp-on
    came_back = threading.Event()
    drv._loop.call_soon_threadsafe(came_back.set)
    assert came_back.wait(5)
    time.sleep(0.2)  # time for a stale write to land, if one were sent (about 1 ms here)
    assert not device.coil(0)


def test_go_safe_says_why_when_the_device_does_not_answer(
        make_driver: Callable[..., ModbusIoDriver]) -> None:
    drv = make_driver(spec(free_port()))
    plc = Scanner(drv)
    t0 = time.monotonic()
    assert not drv.go_safe(safe_image(plc), 0.3)
    assert time.monotonic() - t0 < 0.6
    assert drv.problem().startswith("safe outputs not confirmed: ")
    assert "cannot connect" in drv.problem()


def test_go_safe_all_runs_every_driver_within_one_bound(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    live = make_driver(spec(device.port, name="live"))
    dead = make_driver(spec(free_port(), name="dead"))
    plc = lamp_on(device, live)
    t0 = time.monotonic()
    assert go_safe_all([dead, live], safe_image(plc), 0.4) == {"dead": False, "live": True}
    assert time.monotonic() - t0 < 0.8  # one bound, not one per driver
    assert not device.coil(0)


def test_sim_driver_goes_safe_at_once_unless_offline() -> None:
    io = load_io_image(str(ROOT / "io_images" / "transport.yaml"))
    (driver,) = open_drivers(io)
    image = ProcessImage(io.sizes)
    assert go_safe_all([driver], image) == {"plant": True}
    driver.offline = True  # type: ignore[attr-defined]
    assert not driver.go_safe(image, 0.1)
    driver.close()
    driver.offline = False  # type: ignore[attr-defined]
    assert not driver.go_safe(image, 0.1)


# ----- close -----


def test_close_never_drops_the_pending_outputs(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    for _ in range(5):  # the bug: 4 of 5 shutdowns left the lamp on
        drv = make_driver(spec(device.port))
        plc = lamp_on(device, drv)
        drv.write_outputs(safe_image(plc), plc.now_ns)  # what a shutdown queued
        drv.close()
        assert not device.coil(0)


def test_close_with_a_wedged_io_thread_still_writes_the_pending_outputs(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    drv = make_driver(spec(device.port))
    plc = lamp_on(device, drv)
    assert drv._loop is not None
    drv._loop.call_soon_threadsafe(time.sleep, 2.0)
    time.sleep(0.05)
    drv.write_outputs(safe_image(plc), plc.now_ns)
    drv.close()
    assert not device.coil(0)


# ----- heartbeat and the device's watchdog -----


def heartbeat(period: str = "50ms", **extra: Any) -> dict[str, Any]:
    return {"heartbeat": {"register": 40, "period": period, **extra}}


def beats(device: RemoteIoDevice) -> int:
    return sum(1 for fc, address, _ in device.take_requests() if fc == 6 and address == 40)


def test_heartbeat_arms_the_device_watchdog_and_keeps_it_alive_while_scans_run(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    drv = make_driver(spec(device.port, **heartbeat(watchdog_register=41, watchdog_value=300)))
    plc = lamp_on(device, drv)
    assert device.get(FC_HR, 41) == [300]  # armed at connect
    device.take_requests()
    t0 = time.monotonic()
    while time.monotonic() - t0 < 1.0:  # scans for 1 s: the heartbeat keeps the lamp on
        plc.scan()
        time.sleep(0.01)
    elapsed = time.monotonic() - t0
    sent = beats(device)
    assert 1 <= sent <= elapsed / 0.05 + 2  # at most once per period
    assert device.coil(0) and device.trips == 0
    assert drv.stats().heartbeats >= sent
    # The scans stop (a wedged or killed scan): no more heartbeats, the module trips.
    stopped = time.monotonic()
    assert wait_until(lambda: not device.coil(0), timeout_s=2.0, step_s=0.002)
    assert device.trips == 1 and device.tripped_at is not None
    # Not before the watchdog time after the last beat the module saw (the last beat came
    # before `stopped`, so measuring from `stopped` undercounts on a busy machine), and
    # within the watchdog time and a margin after the scans stopped.
    assert device.tripped_at - device.beat_at >= 0.3 - 0.05
    assert device.beat_at <= stopped + 0.05
    assert device.tripped_at - stopped < 0.3 + 0.5
    # The scans resume: the heartbeat re-arms the module and the lamp comes back.
    assert plc.until(lambda: not device.tripped and device.coil(0), timeout_s=3.0)


def test_without_a_heartbeat_the_device_watchdog_never_trips(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    device.set(FC_HR, 41, [300])  # a timeout, but nobody ever beats
    drv = make_driver(spec(device.port))
    lamp_on(device, drv)
    time.sleep(0.6)
    assert device.coil(0) and device.trips == 0


def test_the_watchdog_register_is_written_again_after_the_device_restarts(
        device: RemoteIoDevice, make_driver: Callable[..., ModbusIoDriver]) -> None:
    drv = make_driver(spec(device.port, **heartbeat(watchdog_register=41, watchdog_value=250)))
    plc = lamp_on(device, drv)
    device.stop()
    assert plc.until(lambda: drv.health() is Health.DOWN, timeout_s=3.0)
    device.start()  # restarted with its watchdog off (0)
    assert plc.until(lambda: device.get(FC_HR, 41) == [250], timeout_s=3.0)


@pytest.mark.parametrize(("value", "expected"), [
    ("100ms", "expected a mapping"),
    ({"register": 40}, "register and period are required"),
    ({"register": 40, "period": "100ms", "every": 1}, "unknown keys"),
    ({"register": -1, "period": "100ms"}, r"heartbeat.register: expected an integer in 0..65535"),
    ({"register": True, "period": "100ms"}, "heartbeat.register: expected an integer"),
    ({"register": 40, "period": 100}, "heartbeat.period: bad duration"),
    ({"register": 40, "period": "1ms"}, r"not within 10ms..60s"),
    ({"register": 40, "period": "2min"}, r"not within 10ms..60s"),
    ({"register": 40, "period": "100ms", "watchdog_register": 41}, "go together"),
    ({"register": 40, "period": "100ms", "watchdog_register": 40, "watchdog_value": 5},
     "is the heartbeat register"),
    ({"register": 40, "period": "100ms", "watchdog_register": 41, "watchdog_value": 70000},
     "watchdog_value: expected an integer in 0..65535"),
    ({"register": 3, "period": "100ms"}, r"hr:3 is already an output channel \(hr:2\+2\)"),
])
def test_bad_heartbeat_params_are_clear_device_errors(value: Any, expected: str) -> None:
    symbols = [*lamp(), sym("a", "%QW0", "hr:2"), sym("b", "%QW1", "hr:3")]
    with pytest.raises(DeviceError, match=expected) as info:
        ModbusIoDriver(spec(502, heartbeat=value), symbols)
    assert isinstance(info.value, ValueError)
    assert str(info.value).startswith(f"driver {DRIVER!r}: heartbeat")
