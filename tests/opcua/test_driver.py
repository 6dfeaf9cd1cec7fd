"""The `kind: opcua` driver against a real `softplc run`: remote inputs read into the local
image, local outputs written to the remote PLC, a rising edge calling a remote method with
done/failed coming back as inputs, go_safe acknowledged; never blocking the caller."""

from __future__ import annotations

import os
import time

import pytest

from softplc.core.image import ProcessImage
from softplc.devices.driver import Health
from softplc.opcua.driver import OpcUaIoDriver
from softplc.program.io_image import parse_io_image
from tests.opcua.conftest import Plc

IO = """
drivers:
  remote: {{kind: opcua, url: "{url}", user: operator, password_env: SOFTPLC_TEST_TOKEN}}
symbols:
  far_s1_i:  {{address: "%IX0.0", type: bool, channel: PLC.Symbols.s1_i}}
  far_m1:    {{address: "%IX0.1", type: bool, channel: PLC.Symbols.m1}}
  stop_done: {{address: "%IX0.2", type: bool, channel: "done:stop_it"}}
  stop_fail: {{address: "%IX0.3", type: bool, channel: "failed:stop_it"}}
  far_hold:  {{address: "%QX0.0", type: bool, channel: PLC.Symbols.hold}}
  stop_it:   {{address: "%QX0.1", type: bool, channel: "call:PLC.Program.Suspend"}}
"""


def _until(check, timeout_s: float = 30.0):  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if value := check():
            return value
        time.sleep(0.05)
    raise AssertionError("condition not met in time")


def test_remote_io_calls_and_go_safe(transport_plc: Plc, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SOFTPLC_TEST_TOKEN", transport_plc.token)
    io = parse_io_image(IO.format(url=transport_plc.url), "remote.yaml")
    driver = OpcUaIoDriver(io.drivers["remote"], list(io.symbols.values()))
    image = ProcessImage(io.sizes)
    sym = io.symbols
    driver.open()
    try:
        def scan() -> ProcessImage:
            began = time.perf_counter()
            driver.read_inputs(image, 0)
            driver.write_outputs(image, 0)
            assert time.perf_counter() - began < 0.05  # the scan side never waits on the net
            return image

        _until(lambda: scan() and driver.health() is Health.OK)
        _until(lambda: scan().get(sym["far_s1_i"].address))  # the remote plant's first part
        image.set(sym["far_hold"].address, 1)
        assert driver.go_safe(image, 10.0)  # written and acknowledged within the bound
        image.set(sym["stop_it"].address, 1)  # rising edge: Suspend the remote program
        _until(lambda: scan().get(sym["stop_done"].address))
        assert not image.get(sym["stop_fail"].address)
        image.set(sym["stop_it"].address, 0)
        _until(lambda: not scan().get(sym["stop_done"].address))
        image.set(sym["stop_it"].address, 1)  # Suspend again: refused (already STOPPED)
        _until(lambda: scan().get(sym["stop_fail"].address))
    finally:
        driver.close()
    assert driver.health() is Health.DOWN
    assert os.environ["SOFTPLC_TEST_TOKEN"]


def test_bad_channels_are_one_clear_error() -> None:
    io = parse_io_image(IO.format(url="opc.tcp://127.0.0.1:1").replace(
        '"done:stop_it"', '"done:nothing"'), "remote.yaml")
    with pytest.raises(ValueError, match="stop_done"):
        OpcUaIoDriver(io.drivers["remote"], list(io.symbols.values()))
