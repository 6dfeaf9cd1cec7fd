"""Modbus RTU remote I/O: the PLC is the master of a serial line (RS-485), each remote device
a unit on it. One driver per unit; the drivers naming one port share one line.

Owns: RtuParams (the serial settings as pymodbus names them, the unit, its timeout and
inter-frame gap), SerialLine (one pymodbus ModbusSerialClient per port: one request at a
time, each after the gap), the lines in use (opened by the first driver of a port, closed by
the last), UnitClient (one unit as the I/O thread's client), RtuTransport and
ModbusRtuDriver. The cycle, plan, backoff, health and go_safe are the Modbus TCP driver's
(modbus_io.py, modbus_link.py): only the wire differs.
Does not know: the scan, the process image, the cycle.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException
from pymodbus.pdu import ModbusPDU

from softplc.core.symbols import DriverSpec, Symbol
from softplc.devices.driver import DriverConfigError
from softplc.devices.modbus_io import ModbusIoDriver
from softplc.devices.modbus_params import Heartbeat, parse_params, timing_problem
from softplc.devices.modbus_plan import Block, IoPlan
from softplc.devices.modbus_requests import ERRORS, Client, write_all
from softplc.devices.modbus_transport import OnLink, Wire

KIND = "modbus_rtu"
PARITIES = ("N", "E", "O")
UNITS = range(1, 248)  # 0 is broadcast (no reply), 248..255 reserved (Modbus serial line 2.2)
FAST_GAP_S = 0.00175  # the spec's fixed 3.5-character time above 19200 baud
LINE_WAIT_S = 2.0  # the longest a request waits for the other units' requests on the line

T = TypeVar("T")


@dataclass(frozen=True, slots=True)
class RtuParams:
    port: str
    unit: int = 1
    baudrate: int = 19200
    parity: str = "N"
    stopbits: int = 1
    bytesize: int = 8
    timeout_s: float = 0.5  # a 125-register reply takes 0.27 s at 9600 baud
    frame_gap_s: float | None = None  # default: 3.5 characters (FAST_GAP_S above 19200)
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    poll: str = "scan"
    heartbeat: Heartbeat | None = None
    word_order: str = "big"  # of 32/64-bit values' registers (modbus_plan.WordOrder)

    @classmethod
    def from_spec(cls, spec: DriverSpec, plan: IoPlan | None = None) -> RtuParams:
        """Raises DriverConfigError (also a ValueError) naming the first problem found."""
        return parse_params(cls, spec, plan, ("port",))

    @property
    def line(self) -> tuple[int, str, int, int]:
        """What every unit on one port must agree on."""
        return self.baudrate, self.parity, self.stopbits, self.bytesize

    @property
    def gap_s(self) -> float:
        """Silence on the line before a request to this unit (the spec's t3.5 by default)."""
        if self.frame_gap_s is not None:
            return float(self.frame_gap_s)
        if self.baudrate > 19200:
            return FAST_GAP_S
        bits = 1 + self.bytesize + (self.parity != "N") + self.stopbits
        return 3.5 * bits / self.baudrate

    def _problem(self) -> str | None:
        gap = self.frame_gap_s
        checks = (
            (isinstance(self.port, str) and bool(self.port),
             "port must be a serial device path such as /dev/ttyUSB0"),
            (_is_int(self.baudrate) and self.baudrate > 0,
             "baudrate must be a positive integer (bits per second)"),
            (self.parity in PARITIES, f"parity must be N, E or O, got {self.parity!r}"),
            (_is_int(self.stopbits) and self.stopbits in (1, 2), "stopbits must be 1 or 2"),
            (_is_int(self.bytesize) and self.bytesize == 8,
             "bytesize must be 8: RTU frames are 8-bit (7 is ASCII mode, not supported)"),
            (gap is None or (_number(gap) and 0 <= gap <= 1.0),
             "frame_gap_s must be a number of seconds in 0..1"),
        )
        problem = next((msg for ok, msg in checks if not ok), None)
        return problem or timing_problem(self, self.poll, UNITS)


def line_text(line: tuple[int, str, int, int]) -> str:
    baudrate, parity, stopbits, bytesize = line
    return f"{baudrate} {bytesize}{parity}{stopbits}"


class SerialLine:
    """One serial port (pyserial opens it exclusively), shared by the units on it: one request
    at a time, each after its unit's gap since the end of the last frame."""

    def __init__(self, port: str, params: RtuParams) -> None:
        self.port, self.line = port, params.line
        self._lock = threading.Lock()
        self._client = ModbusSerialClient(
            port, framer=FramerType.RTU, baudrate=params.baudrate, parity=params.parity,
            stopbits=params.stopbits, bytesize=params.bytesize, timeout=params.timeout_s,
            retries=0)
        self._quiet_since = 0.0  # time.monotonic() at the end of the last frame

    @property
    def is_open(self) -> bool:
        return bool(self._client.connected)

    def open(self) -> bool:
        """Open the port if no unit has (False when it cannot be, or stays busy)."""
        try:
            return self.request(lambda _client: True, 0.1, 0.0, LINE_WAIT_S)
        except (ConnectionException, TimeoutError):
            return False

    def close(self) -> None:
        with self._lock:
            self._client.close()  # type: ignore[no-untyped-call]

    def request(self, call: Callable[[ModbusSerialClient], T], timeout_s: float, gap_s: float,
                wait_s: float) -> T:
        """`call` on the open port, alone on the line. Raises TimeoutError when the line stays
        busy for wait_s, ConnectionException when the port cannot be opened."""
        if not self._lock.acquire(timeout=max(0.0, wait_s)):
            raise TimeoutError(f"{self.port}: line busy for {wait_s:g}s")
        try:
            if not self._client.connect():
                raise ConnectionException(f"cannot open {self.port}")
            # One client, several units with their own timeouts: pymodbus reads it per request.
            self._client.comm_params.timeout_connect = timeout_s
            pause = self._quiet_since + gap_s - time.monotonic()
            if pause > 0:
                time.sleep(pause)
            try:
                return call(self._client)
            finally:
                self._quiet_since = time.monotonic()
        finally:
            self._lock.release()


class _Lines:
    """The lines in use, by real port path: each opened by its first unit, closed by its last.
    Two drivers on one port must agree on its settings and have different units."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lines: dict[str, tuple[SerialLine, dict[RtuTransport, int]]] = {}

    def attach(self, user: RtuTransport) -> SerialLine:
        p, key = user.params, os.path.realpath(user.params.port)
        with self._lock:
            line, users = self._lines.get(key) or (SerialLine(p.port, p), {})
            if users and line.line != p.line:
                raise DriverConfigError(
                    f"driver {user.name!r}: port {p.port} is in use at {line_text(line.line)}, "
                    f"this driver asks for {line_text(p.line)}")
            other = next((u.name for u, unit in users.items()
                          if unit == p.unit and u is not user), None)
            if other is not None:
                raise DriverConfigError(
                    f"driver {user.name!r}: unit {p.unit} on {p.port} is driver {other!r}'s")
            users[user] = p.unit
            self._lines[key] = line, users
            return line

    def detach(self, user: RtuTransport) -> None:
        key = os.path.realpath(user.params.port)
        with self._lock:
            line, users = self._lines.get(key, (None, {}))
            users.pop(user, None)
            if line is None or users:
                return
            del self._lines[key]
        line.close()


LINES = _Lines()


class UnitClient:
    """One unit of a line, as the I/O thread's client. The line's blocking requests run in a
    worker thread; close() leaves the port open for the other units."""

    def __init__(self, line: SerialLine, params: RtuParams, on_link: OnLink) -> None:
        self._line, self._params, self._on_link = line, params, on_link
        self._connected = False

    @property
    def connected(self) -> bool:
        return self._connected

    async def connect(self) -> bool:
        self._connected = await asyncio.to_thread(self._line.open)
        if self._connected:
            self._on_link(True)
        return self._connected

    def close(self) -> None:
        self._connected = False

    def read_coils(self, address: int, *, count: int, device_id: int) -> Any:
        return self._request(lambda c: c.read_coils(address, count=count, device_id=device_id))

    def read_discrete_inputs(self, address: int, *, count: int, device_id: int) -> Any:
        return self._request(
            lambda c: c.read_discrete_inputs(address, count=count, device_id=device_id))

    def read_holding_registers(self, address: int, *, count: int, device_id: int) -> Any:
        return self._request(
            lambda c: c.read_holding_registers(address, count=count, device_id=device_id))

    def read_input_registers(self, address: int, *, count: int, device_id: int) -> Any:
        return self._request(
            lambda c: c.read_input_registers(address, count=count, device_id=device_id))

    def write_coils(self, address: int, values: list[bool], *, device_id: int) -> Any:
        return self._request(lambda c: c.write_coils(address, values, device_id=device_id))

    def write_registers(self, address: int, values: list[int], *, device_id: int) -> Any:
        return self._request(lambda c: c.write_registers(address, values, device_id=device_id))

    def write_register(self, address: int, value: int, *, device_id: int) -> Any:
        return self._request(lambda c: c.write_register(address, value, device_id=device_id))

    async def _request(self, call: Callable[[ModbusSerialClient], ModbusPDU]) -> ModbusPDU:
        p = self._params
        try:
            return await asyncio.to_thread(self._line.request, call, p.timeout_s, p.gap_s,
                                           LINE_WAIT_S)
        finally:
            if self._connected and not self._line.is_open:  # the port went away (unplugged)
                self._connected = False
                self._on_link(False)


class RtuTransport:
    """One unit on a shared serial line (see modbus_transport.Transport)."""

    def __init__(self, name: str, params: RtuParams) -> None:
        self.name, self.params = name, params
        self.where = f"{params.port} unit {params.unit}"
        self.silence = (f"unit {params.unit} on {params.port} did not answer within "
                        f"{params.timeout_s:g} s")
        self._line: SerialLine | None = None

    def client(self, on_link: OnLink) -> Client:
        line = self._line
        if line is None:
            raise ConnectionException(f"driver {self.name!r}: not attached to {self.params.port}")
        client: Client = UnitClient(line, self.params, on_link)
        return client

    def attach(self) -> None:
        if self._line is None:
            self._line = LINES.attach(self)

    def detach(self) -> None:
        if self._line is not None:
            LINES.detach(self)
            self._line = None

    def write_direct(self, blocks: Sequence[Block], outputs: Sequence[list[Any]],
                     deadline: float) -> str:
        left = deadline - time.monotonic()
        if left <= 0:
            return "no time left for a direct write"
        attached = self._line is not None
        p = self.params
        try:
            line = self._line or LINES.attach(self)  # closed: borrow the line for this write
            line.request(lambda c: write_all(c, p.unit, blocks, outputs), min(p.timeout_s, left),
                         p.gap_s, left)
        except (*ERRORS, DriverConfigError) as exc:
            return f"direct write: {exc or type(exc).__name__}"
        finally:
            if not attached:
                LINES.detach(self)
        return ""


def _rtu(spec: DriverSpec, plan: IoPlan) -> RtuTransport:
    return RtuTransport(spec.name, RtuParams.from_spec(spec, plan))


RTU = Wire(KIND, _rtu)


class ModbusRtuDriver(ModbusIoDriver):
    """One unit on a serial line: the Modbus remote-I/O driver with the RTU wire."""

    def __init__(self, spec: DriverSpec, symbols: Sequence[Symbol]) -> None:
        super().__init__(spec, symbols, RTU)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
