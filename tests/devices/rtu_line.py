"""A serial line for Modbus RTU tests: a pair of virtual serial ports made by Debian's socat,
with a real pymodbus 3.16.1 RTU server (ModbusSerialServer, one SimDevice per unit) on one
end, in its own thread and loop; the driver under test opens the other end.

`mute(unit)` makes a unit stop answering (its replies are dropped before they reach the
wire, as a device that lost power would). Every call into the server is bounded."""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from pymodbus.server import ModbusSerialServer
from pymodbus.simulator import DataType, SimData, SimDevice

FC_COIL, FC_DI, FC_HR, FC_IR = 1, 2, 3, 4
SIZE = 64


def _device(unit: int) -> SimDevice:
    return SimDevice(
        id=unit,
        simdata=(
            [SimData(0, values=[False] * SIZE, datatype=DataType.BITS)],
            [SimData(0, values=[False] * SIZE, datatype=DataType.BITS)],
            [SimData(0, values=[0] * SIZE, datatype=DataType.REGISTERS)],
            [SimData(0, values=[0] * SIZE, datatype=DataType.REGISTERS)],
        ),
    )


class RtuLine:
    """`master` is the port path the driver opens; units answer on the other end."""

    def __init__(self, tmp_path: Path, units: tuple[int, ...] = (1, 2),
                 baudrate: int = 19200) -> None:
        socat = shutil.which("socat")
        if socat is None:
            pytest.skip("socat is not installed (apt-get install socat): no virtual serial line")
        self.master, self._slave = str(tmp_path / "ttyMASTER"), str(tmp_path / "ttySLAVE")
        self.units, self.baudrate = units, baudrate
        self.muted: set[int] = set()
        self.requests: dict[int, int] = {}  # unit -> requests seen
        self._socat = subprocess.Popen(
            [socat, f"pty,raw,echo=0,link={self.master}", f"pty,raw,echo=0,link={self._slave}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.server: ModbusSerialServer | None = None

    def start(self) -> RtuLine:
        deadline = time.monotonic() + 5
        while not (Path(self.master).exists() and Path(self._slave).exists()):
            if time.monotonic() > deadline or self._socat.poll() is not None:
                self.dispose()
                raise AssertionError("socat did not make the pty pair within 5 s")
            time.sleep(0.01)
        self._thread.start()
        self._call(self._start())
        return self

    async def _start(self) -> None:
        self.server = ModbusSerialServer(
            [_device(u) for u in self.units], port=self._slave, baudrate=self.baudrate,
            trace_packet=self._trace)
        await self.server.serve_forever(background=True)

    def _trace(self, sending: bool, frame: bytes) -> bytes:
        unit = frame[0] if frame else -1
        if not sending:
            self.requests[unit] = self.requests.get(unit, 0) + 1
            return frame
        return b"" if unit in self.muted else frame

    def _call(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(2.0)

    def mute(self, unit: int, muted: bool = True) -> None:
        (self.muted.add if muted else self.muted.discard)(unit)

    def set(self, unit: int, fc: int, address: int, values: list[Any]) -> None:
        assert self.server is not None
        self._call(self.server.async_setValues(unit, fc, address, values))

    def get(self, unit: int, fc: int, address: int, count: int) -> list[Any]:
        assert self.server is not None
        return list(self._call(self.server.async_getValues(unit, fc, address, count)))

    def coil(self, unit: int, address: int) -> bool:
        return bool(self.get(unit, FC_COIL, address, 1)[0])

    def dispose(self) -> None:
        if self.server is not None and self._thread.is_alive():
            # A test's cleanup: the line goes whatever the server says.
            with contextlib.suppress(Exception):
                self._call(self.server.shutdown())  # type: ignore[no-untyped-call]
            self.server = None
        if self._thread.is_alive():
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(2)
        if self._socat.poll() is None:
            self._socat.terminate()
            try:
                self._socat.wait(2)
            except subprocess.TimeoutExpired:
                self._socat.kill()
                self._socat.wait(2)
