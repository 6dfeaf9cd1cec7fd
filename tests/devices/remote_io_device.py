"""A simulated Modbus TCP remote-I/O module with its own communication watchdog, for tests.

A real pymodbus 3.16.1 server on 127.0.0.1 (own thread and asyncio loop) with 64 coils,
discrete inputs, holding and input registers, behaving like the bus couplers of WAGO or
Beckhoff: holding register `watchdog_register` holds the watchdog timeout in milliseconds
(0: off); once armed, the holding register `heartbeat_register` must change at least once per
timeout. When it does not, the module trips: every coil drops to 0 (its fail-safe state) and is
held there until the heartbeat changes again. The watchdog arms at the first heartbeat change,
so a controller that never sends one (or a timeout of 0) leaves the outputs alone.

Unlike tests.support.SimModbusServer (a plain server), it has this watchdog and a latency:
`latency_s` delays every request from the network by that much before it takes effect and is
answered, like a real module behind a real network (a few ms); the test side's own reads and
writes are not delayed.
"""

from __future__ import annotations

import asyncio
import contextvars
import threading
import time
from typing import Any

from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from tests.support import free_port

FC_COIL, FC_DI, FC_HR, FC_IR = 1, 2, 3, 4
SIZE = 64  # per table; a multiple of 16 (pymodbus checks bit areas per 16-bit word)
CHECK_S = 0.005  # how often the module's watchdog looks at the heartbeat register
# Set in the tasks of the module itself and of the test side: their accesses are not requests.
_INTERNAL: contextvars.ContextVar[bool] = contextvars.ContextVar("internal", default=False)


class RemoteIoDevice:
    """Start with start(), end with dispose(). Thread-safe accessors for the test side."""

    def __init__(self, port: int | None = None, *, heartbeat_register: int = 40,
                 watchdog_register: int = 41, timeout_ms: int = 0,
                 latency_s: float = 0.0) -> None:
        self.port = port or free_port()
        self.latency_s = latency_s
        self.heartbeat_register, self.watchdog_register = heartbeat_register, watchdog_register
        self.initial_timeout_ms = timeout_ms
        self.trips = 0
        self.tripped_at: float | None = None  # time.monotonic() of the latest trip
        self.requests: list[tuple[int, int, int]] = []  # (function code, address, count)
        self._lock = threading.Lock()
        self._armed = False
        self._tripped = False
        self._last_beat = 0
        self._beat_at = 0.0
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="remote-io", daemon=True)
        self.thread.start()
        self.server: ModbusTcpServer | None = None
        self._monitor: asyncio.Future[None] | None = None

    # -- life --------------------------------------------------------------------------------

    def start(self) -> RemoteIoDevice:
        self._call(self._start())
        return self

    def stop(self) -> None:
        if self.server is not None:
            self._call(self._stop())

    def dispose(self) -> None:
        self.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=2)
        self.loop.close()

    async def _start(self) -> None:
        _INTERNAL.set(True)
        bits = [SimData(0, values=[False] * SIZE, datatype=DataType.BITS)]
        words = [SimData(0, values=[0] * SIZE, datatype=DataType.REGISTERS)]
        device = SimDevice(id=0, simdata=(bits, list(bits), words, list(words)),
                           action=self._action)
        self.server = ModbusTcpServer(device, address=("127.0.0.1", self.port),
                                      trace_pdu=self._trace)
        await self.server.serve_forever(background=True)
        await self.server.async_setValues(0, FC_HR, self.watchdog_register,
                                          [self.initial_timeout_ms])
        self._armed = self._tripped = False
        self._last_beat, self._beat_at = 0, time.monotonic()
        self._monitor = asyncio.ensure_future(self._watch())

    async def _stop(self) -> None:
        if self._monitor is not None:
            self._monitor.cancel()
            self._monitor = None
        assert self.server is not None
        await self.server.shutdown()
        self.server = None

    def _call(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout=5)

    async def _action(self, fc: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | None) -> None:
        if self.latency_s and not _INTERNAL.get():
            await asyncio.sleep(self.latency_s)

    @staticmethod
    async def _internal(coro: Any) -> Any:
        _INTERNAL.set(True)
        return await coro

    def _trace(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if not sending:
            with self._lock:
                self.requests.append((pdu.function_code, pdu.address, pdu.count))
        return pdu

    # -- the module's communication watchdog -------------------------------------------------

    async def _watch(self) -> None:
        _INTERNAL.set(True)
        while True:
            await asyncio.sleep(CHECK_S)
            await self._check()

    async def _check(self) -> None:
        assert self.server is not None
        beat = (await self.server.async_getValues(0, FC_HR, self.heartbeat_register, 1))[0]
        timeout_ms = (await self.server.async_getValues(0, FC_HR, self.watchdog_register, 1))[0]
        now = time.monotonic()
        if beat != self._last_beat:
            self._last_beat, self._beat_at = beat, now
            self._armed, self._tripped = True, False
        elif (self._armed and not self._tripped and timeout_ms > 0
              and now - self._beat_at > timeout_ms / 1000):
            self._tripped, self.tripped_at = True, now
            self.trips += 1
        if self._tripped:
            coils = await self.server.async_getValues(0, FC_COIL, 0, SIZE)
            if any(coils):
                await self.server.async_setValues(0, FC_COIL, 0, [False] * SIZE)

    # -- the test side -----------------------------------------------------------------------

    @property
    def beat_at(self) -> float:
        """time.monotonic() when the module last saw the heartbeat change."""
        return self._beat_at

    @property
    def tripped(self) -> bool:
        return self._tripped

    def get(self, fc: int, address: int, count: int = 1) -> list[Any]:
        assert self.server is not None
        return list(self._call(self._internal(self.server.async_getValues(0, fc, address, count))))

    def set(self, fc: int, address: int, values: list[Any]) -> None:
        assert self.server is not None
        self._call(self._internal(self.server.async_setValues(0, fc, address, values)))

    def coil(self, address: int) -> bool:
        return bool(self.get(FC_COIL, address)[0])

    def take_requests(self) -> list[tuple[int, int, int]]:
        with self._lock:
            taken, self.requests = self.requests, []
        return taken
