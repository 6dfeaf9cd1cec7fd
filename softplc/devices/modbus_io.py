"""Modbus TCP remote I/O: the PLC is the client, a remote I/O module is the server.

Owns: the I/O thread with its own asyncio loop and pymodbus client, the last good inputs, the
latest outputs, their acknowledgement, go_safe (a confirmed write within a bound), the
heartbeat that keeps the device's own watchdog alive, health and stats. Channel planning is
modbus_plan.py, params modbus_params.py, the requests themselves modbus_requests.py.
Does not know: the scan, the Petri net, the HMI.

Threading: read_inputs/write_outputs never touch the network; they swap values with the I/O
thread under a lock. write_outputs wakes it for one cycle: every write range, the heartbeat
when due, then every read range, one request each. read_inputs wakes it only if no outputs
came since the last read (first scan, read-only callers). Wake-ups during a cycle coalesce
into one more cycle with the latest outputs. Scan k sees the inputs of the last cycle
completed before its read_inputs. Each output image handed over has a sequence number; the
I/O thread acknowledges the number once the device has answered every write of it.

go_safe hands over the safe image, cuts short any reconnect backoff and waits for its
acknowledgement; if the I/O thread has not confirmed within half the bound (wedged, dead,
closed), it writes on a fresh connection of its own within the rest. close() lets the I/O
thread flush the latest unacknowledged outputs before it ends, and writes them directly if
the thread cannot: a stop never drops the safe write.

Health: OK when connected and the last cycle succeeded; DEGRADED when connected but the last
cycle failed or none has completed on this connection yet; DOWN when not connected (never,
lost, closed). DROP_AFTER failed cycles in a row (stale for at most that many cycles) drop
the connection; reconnects back off from reconnect_min_s, doubling up to reconnect_max_s."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymodbus.client import AsyncModbusTcpClient

from softplc.core.image import BoolArray, ProcessImage, WordArray
from softplc.core.symbols import DriverSpec, Symbol
from softplc.devices.driver import Health
from softplc.devices.modbus_params import Heartbeat, ModbusParams
from softplc.devices.modbus_plan import (
    MAX_OFFSET,
    Block,
    Channel,
    IoPlan,
    Table,
    channel_problems,
    parse_channel,
    plan_channels,
)
from softplc.devices.modbus_requests import (
    ERRORS,
    RemoteError,
    quiet_pymodbus,
    read_block,
    write_block,
    write_direct,
    write_word,
)

__all__ = [
    "MAX_OFFSET", "Block", "Channel", "Heartbeat", "IoPlan", "IoStats", "ModbusIoDriver",
    "ModbusParams", "RemoteError", "Table", "channel_problems", "parse_channel", "plan_channels",
]

log = logging.getLogger(__name__)

DROP_AFTER = 3  # failed cycles in a row on one connection before it is dropped
CLOSE_JOIN_S = 1.0  # the I/O thread's time to flush and end on close()
CLOSE_DIRECT_S = 0.5  # then, if it could not, a direct write of the pending outputs
THREAD_SHARE = 0.5  # of go_safe's bound, for the I/O thread before the direct write
_CANCEL_ROUNDS = 50

Outputs = tuple[list[Any], ...]


@dataclass(frozen=True, slots=True)
class IoStats:
    """For the runtime's fault policy. last_ok_ns is the now_ns of the scan that first received
    the inputs of the latest successful cycle (None before the first). consecutive_failures
    counts failed cycles and failed connect attempts since the last successful cycle."""

    connected: bool
    last_ok_ns: int | None
    consecutive_failures: int
    stale_scans: int  # read_inputs calls since fresh inputs were last delivered
    cycles_ok: int
    cycles_failed: int
    last_error: str
    heartbeats: int = 0  # heartbeat writes the device acknowledged


_HEALTH = {(True, True): Health.OK, (True, False): Health.DEGRADED}


class ModbusIoDriver:
    """Driver for one remote I/O module. See the module docstring for threading and health."""

    def __init__(self, spec: DriverSpec, symbols: Sequence[Symbol]) -> None:
        if spec.kind != "modbus":
            raise ValueError(f"driver {spec.name!r}: kind {spec.kind!r}, expected 'modbus'")
        foreign = [s.name for s in symbols if s.driver != spec.name]
        if foreign:
            raise ValueError(f"driver {spec.name!r}: symbols {foreign} belong to another driver")
        self.name = spec.name
        self.plan = plan_channels(symbols)
        self.params = ModbusParams.from_spec(spec, self.plan)
        self._read_index = [np.array(b.image_index, dtype=np.intp) for b in self.plan.reads]
        self._write_index = [np.array(b.image_index, dtype=np.intp) for b in self.plan.writes]
        self._lock = threading.Lock()
        self._acked = threading.Condition(self._lock)
        # Written by the I/O thread, read by the scan thread; under _lock.
        self._inputs: tuple[BoolArray | WordArray, ...] | None = None
        self._ok_seq = 0
        self._cycles_failed = 0
        self._failures = 0
        self._connected = False
        self._last_cycle_ok = False
        self._last_error = ""
        self._heartbeats = 0
        self._ack_seq = 0  # the newest output image the device acknowledged
        # Written by the scan thread, read by the I/O thread; under _lock.
        self._outputs: Outputs | None = None
        self._out_seq = 0  # the newest output image handed over
        self._safe_seq = 0  # the newest one go_safe handed over
        self._safe_error = ""  # why the latest go_safe was not confirmed
        self._closing = False
        # Scan thread only.
        self._seen_seq = 0
        self._last_ok_ns: int | None = None
        self._stale_scans = 0
        self._wrote_since_read = False
        # I/O thread plumbing; None while closed.
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake = asyncio.Event()
        self._urgent = asyncio.Event()  # cuts a reconnect pause short (go_safe, close)
        # I/O thread only.
        self._fails_on_link = 0
        self._fresh_link = False  # the device's watchdog register is written first
        self._beat = 0
        self._beat_due = 0.0

    # ----- scan side -----

    def open(self) -> None:
        if self._thread is not None:
            return
        quiet_pymodbus()
        self._closing = False
        self._loop = asyncio.new_event_loop()
        self._wake, self._urgent = asyncio.Event(), asyncio.Event()
        self._thread = threading.Thread(
            target=self._thread_main, args=(self._loop,), name=f"modbus-io-{self.name}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        """Stop the I/O thread, after it wrote the latest outputs if the device had not yet
        acknowledged them; if it cannot within CLOSE_JOIN_S, write them directly. With nothing
        to write, the thread is stopped at once (a close never waits for a connect)."""
        thread, loop = self._thread, self._loop
        if thread is None or loop is None:
            return
        with self._lock:
            self._closing = True
        if self._pending() is None:  # nothing to flush: do not wait for a connect under way
            with contextlib.suppress(RuntimeError):  # the loop has already ended
                loop.call_soon_threadsafe(loop.stop)
        else:
            self._trigger(urgent=True)
        thread.join(timeout=CLOSE_JOIN_S)
        if thread.is_alive():
            with contextlib.suppress(RuntimeError):  # the loop has already ended
                loop.call_soon_threadsafe(loop.stop)
            log.warning(
                "modbus driver %s: I/O thread did not stop within %ss", self.name, CLOSE_JOIN_S
            )
        self._thread = self._loop = None
        pending = self._pending()
        if pending is not None:
            self._direct(*pending, time.monotonic() + CLOSE_DIRECT_S)
        with self._lock:
            self._connected = self._last_cycle_ok = False

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        with self._lock:
            inputs, seq = self._inputs, self._ok_seq
        # Wake the I/O thread only after the copy: scan k must not see a cycle it started.
        if not self._wrote_since_read:
            self._trigger()
        self._wrote_since_read = False
        if seq != self._seen_seq:
            self._seen_seq, self._last_ok_ns, self._stale_scans = seq, now_ns, 0
        else:
            self._stale_scans += 1
        if inputs is None:
            return
        for block, index, values in zip(self.plan.reads, self._read_index, inputs, strict=True):
            (image.ix if block.table.is_bit else image.iw)[index] = values

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        self._hand_over(image, safe=False)
        self._wrote_since_read = True
        self._trigger()

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool:
        """Write the outputs of `image` and wait for the device's acknowledgement, at most
        timeout_s. Replaces any queued outputs; see the module docstring for the fallback."""
        deadline = time.monotonic() + timeout_s
        outputs, seq = self._hand_over(image, safe=True)
        if not self.plan.writes:
            return self._safe_result(True, "")
        thread = self._thread
        if thread is not None and thread.is_alive():
            self._trigger(urgent=True)
            if self._wait_ack(seq, time.monotonic() + timeout_s * THREAD_SHARE):
                return self._safe_result(True, "")
        why = self._direct(outputs, seq, deadline)
        confirmed = self._wait_ack(seq, time.monotonic())  # the thread may have made it
        return self._safe_result(confirmed, "" if confirmed else why)

    def health(self) -> Health:
        if self._thread is None:
            return Health.DOWN
        with self._lock:
            return _HEALTH.get((self._connected, self._last_cycle_ok), Health.DOWN)

    def problem(self) -> str:
        with self._lock:
            if self._safe_error:
                return self._safe_error
        if self._thread is None:
            return "closed"
        with self._lock:
            if self._connected and self._last_cycle_ok:
                return ""
            if self._last_error:
                return self._last_error
            where = f"{self.params.host}:{self.params.port}"
            return "no cycle completed yet" if self._connected else f"not connected to {where}"

    def stats(self) -> IoStats:
        with self._lock:
            return IoStats(
                connected=self._connected,
                last_ok_ns=self._last_ok_ns,
                consecutive_failures=self._failures,
                stale_scans=self._stale_scans,
                cycles_ok=self._ok_seq,
                cycles_failed=self._cycles_failed,
                last_error=self._last_error,
                heartbeats=self._heartbeats,
            )

    def _hand_over(self, image: ProcessImage, *, safe: bool) -> tuple[Outputs, int]:
        outputs = tuple(
            (image.qx if block.table.is_bit else image.qw)[index].tolist()
            for block, index in zip(self.plan.writes, self._write_index, strict=True)
        )
        with self._lock:
            self._out_seq += 1
            self._outputs = outputs
            if safe:
                self._safe_seq = self._out_seq
            return outputs, self._out_seq

    def _pending(self) -> tuple[Outputs, int] | None:
        """The latest outputs if the device has not acknowledged them."""
        with self._lock:
            if not self.plan.writes or self._outputs is None or self._ack_seq >= self._out_seq:
                return None
            return self._outputs, self._out_seq

    def _wait_ack(self, seq: int, until: float) -> bool:
        with self._acked:
            return self._acked.wait_for(
                lambda: self._ack_seq >= seq, timeout=max(0.0, until - time.monotonic())
            )

    def _ack(self, seq: int) -> None:
        with self._acked:
            if seq > self._ack_seq:
                self._ack_seq = seq
                self._acked.notify_all()

    def _safe_result(self, confirmed: bool, why: str) -> bool:
        with self._lock:
            self._safe_error = "" if confirmed else f"safe outputs not confirmed: {why}"
        return confirmed

    def _trigger(self, *, urgent: bool = False) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # closed by close() in another thread
            loop.call_soon_threadsafe(self._wake.set)
            if urgent:
                loop.call_soon_threadsafe(self._urgent.set)

    def _direct(self, outputs: Outputs, seq: int, deadline: float) -> str:
        """Write `outputs` on a fresh connection of our own (the I/O thread's may be wedged)
        within `deadline`; acknowledge `seq` when the device answered. "" or why not."""
        why = write_direct(self.params, self.plan.writes, outputs, deadline)
        if not why:
            self._ack(seq)
        return why

    # ----- I/O thread -----

    def _thread_main(self, loop: asyncio.AbstractEventLoop) -> None:
        asyncio.set_event_loop(loop)
        task = loop.create_task(self._run())
        task.add_done_callback(self._on_run_done)
        try:
            with contextlib.suppress(RuntimeError):  # loop.stop() by close(): thread wedged
                loop.run_until_complete(asyncio.wait([task]))
        finally:
            # asyncio.wait_for (3.11) swallows a cancel that coincides with the completion of
            # what it waits for (here: a refused connect), so one cancel is not enough.
            for _ in range(_CANCEL_ROUNDS):
                if task.done():
                    break
                task.cancel()
                loop.run_until_complete(asyncio.wait([task], timeout=0.01))
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    def _on_run_done(self, task: asyncio.Task[None]) -> None:
        if task.cancelled() or task.exception() is None:
            return
        exc = task.exception()
        log.error("modbus driver %s: I/O task crashed", self.name, exc_info=exc)
        with self._lock:
            self._connected = self._last_cycle_ok = False
            self._last_error = f"I/O task crashed: {exc!r}"

    async def _run(self) -> None:
        p = self.params
        client = AsyncModbusTcpClient(
            p.host,
            port=p.port,
            timeout=p.timeout_s,
            retries=0,
            reconnect_delay=0,  # reconnection and its backoff are ours, below
            trace_connect=self._on_link,
        )
        try:
            await self._serve(client)
            await self._flush(client)
        finally:
            client.close()
            self._on_link(False)
            await asyncio.sleep(0)  # let the transport's close callback release the socket

    async def _serve(self, client: AsyncModbusTcpClient) -> None:
        p = self.params
        backoff = p.reconnect_min_s
        while not self._closing:
            if not client.connected:
                if not await client.connect():
                    self._note_failure(f"cannot connect to {p.host}:{p.port}", cycle=False)
                    await self._pause(backoff)
                    backoff = min(2 * backoff, p.reconnect_max_s)
                continue
            await self._wake.wait()
            self._wake.clear()
            if self._closing or not client.connected:
                continue
            if await self._cycle(client):
                backoff = p.reconnect_min_s
            elif self._fails_on_link >= DROP_AFTER:
                log.warning("modbus driver %s: dropping the connection", self.name)
                client.close()  # a closing client reports no disconnect: do it here
                self._on_link(False)
                await self._pause(backoff)
                backoff = min(2 * backoff, p.reconnect_max_s)

    async def _pause(self, seconds: float) -> None:
        """A reconnect backoff that a safe write or close cuts short; while a safe write waits
        for its acknowledgement, never longer than reconnect_min_s."""
        with self._lock:
            if self._safe_seq > self._ack_seq:
                seconds = min(seconds, self.params.reconnect_min_s)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._urgent.wait(), seconds)
        self._urgent.clear()

    async def _flush(self, client: AsyncModbusTcpClient) -> None:
        """On close: the latest outputs, if the device has not acknowledged them."""
        pending = self._pending()
        if pending is None:
            return
        try:
            if not client.connected and not await client.connect():
                return
            await self._write_outputs(client, *pending)
        except ERRORS as exc:
            log.warning("modbus driver %s: final write failed: %s", self.name, exc)

    def _on_link(self, connected: bool) -> None:
        with self._lock:
            changed = connected != self._connected
            self._connected, self._last_cycle_ok = connected, False
        self._fails_on_link = 0
        self._fresh_link = connected
        if not connected:
            self._wake.set()  # so that _run notices and reconnects
        if changed:
            p = self.params
            state = "connected to" if connected else "disconnected from"
            log.info("modbus driver %s: %s %s:%s", self.name, state, p.host, p.port)

    async def _cycle(self, client: AsyncModbusTcpClient) -> bool:
        with self._lock:
            outputs, seq = self._outputs, self._out_seq
        try:
            await self._arm_watchdog(client)
            if outputs is not None:
                await self._write_outputs(client, outputs, seq)
            await self._heartbeat(client)
            inputs = tuple([await read_block(client, b, self.params.unit) for b in self.plan.reads])
        except ERRORS as exc:
            self._fails_on_link += 1
            self._note_failure(str(exc) or type(exc).__name__, cycle=True)
            return False
        self._fails_on_link = 0
        with self._lock:
            self._inputs = inputs
            self._ok_seq += 1
            self._failures = 0
            self._last_cycle_ok = True
        return True

    async def _write_outputs(self, client: AsyncModbusTcpClient, outputs: Outputs,
                             seq: int) -> None:
        """Every write range of `outputs`, then acknowledge `seq`. A safe image handed over
        meanwhile replaces a stale one before its next request goes out."""
        blocks = self.plan.writes
        i = 0
        while i < len(blocks):
            with self._lock:
                if self._safe_seq > seq:
                    outputs, seq, i = self._outputs or outputs, self._out_seq, 0
            await write_block(client, blocks[i], outputs[i], self.params.unit)
            i += 1
        self._ack(seq)

    async def _arm_watchdog(self, client: AsyncModbusTcpClient) -> None:
        beat = self.params.heartbeat
        if not self._fresh_link or beat is None or beat.watchdog_register is None:
            return
        await write_word(client, beat.watchdog_register, beat.watchdog_value or 0,
                         self.params.unit)
        self._fresh_link = False

    async def _heartbeat(self, client: AsyncModbusTcpClient) -> None:
        beat = self.params.heartbeat
        now = time.monotonic()
        if beat is None or now < self._beat_due:
            return
        value = (self._beat + 1) & 0xFFFF
        await write_word(client, beat.register, value, self.params.unit)
        self._beat, self._beat_due = value, now + beat.period_ns / 1e9
        with self._lock:
            self._heartbeats += 1

    def _note_failure(self, error: str, *, cycle: bool) -> None:
        with self._lock:
            first = self._failures == 0
            self._failures += 1
            self._cycles_failed += cycle
            self._last_cycle_ok = False
            self._last_error = error
        if first:
            log.warning("modbus driver %s: %s", self.name, error)
