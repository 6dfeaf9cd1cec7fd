"""The device side of a Modbus remote I/O driver (TCP or RTU): its I/O thread and what it
shares with the scan thread.

Owns: LinkState (values swapped between the scan thread and the I/O thread under one lock:
the last good inputs, the latest outputs and their acknowledgement, health counters) and
IoLink (the I/O thread with its own asyncio loop and its transport's client: connect with backoff,
one cycle per wake-up (every write range, the heartbeat when due, every read range), drop a
connection after DROP_AFTER failed cycles, flush the latest outputs on close).
Does not know: the process image, the scan, go_safe's fallback (modbus_io.py has them), the
wire (TCP socket or serial line: modbus_transport.py, modbus_rtu.py).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from pymodbus.exceptions import ModbusIOException

from softplc.core.image import BoolArray, WordArray
from softplc.devices.modbus_plan import IoPlan
from softplc.devices.modbus_requests import ERRORS, Client, read_block, write_block, write_word
from softplc.devices.modbus_transport import Transport

log = logging.getLogger("softplc.devices.modbus_io")  # one logger for the whole driver

DROP_AFTER = 3  # failed cycles in a row on one connection before it is dropped
# Failed cycles in a row before an answering device counts as silent (health DEGRADED, which
# the device fault policy judges): one timed-out request is a slow reply (a busy host, issue
# 26), two are a device that stopped answering, silent within 2 x timeout_s (docs/faults.md).
SILENT_AFTER = 2
_CANCEL_ROUNDS = 50

Outputs = tuple[list[Any], ...]


@dataclass(slots=True)
class LinkState:
    """Shared by the scan thread and the I/O thread; every field under `lock` (`closing` is
    also read without it: a stale read costs one more loop turn)."""

    has_writes: bool
    lock: threading.Lock = field(default_factory=threading.Lock)
    acked: threading.Condition = field(init=False)
    # Written by the I/O thread.
    inputs: tuple[BoolArray | WordArray, ...] | None = None
    ok_seq: int = 0
    cycles_failed: int = 0
    failures: int = 0
    silent: int = 0  # failed cycles in a row in which the device did not answer at all
    connected: bool = False
    last_cycle_ok: bool = False
    last_error: str = ""
    heartbeats: int = 0
    ack_seq: int = 0  # the newest output image the device acknowledged
    # Written by the scan thread.
    outputs: Outputs | None = None
    out_seq: int = 0  # the newest output image handed over
    safe_seq: int = 0  # the newest one go_safe handed over
    safe_error: str = ""  # why the latest go_safe was not confirmed
    closing: bool = False

    def __post_init__(self) -> None:
        self.acked = threading.Condition(self.lock)

    def pending(self) -> tuple[Outputs, int] | None:
        """The latest outputs if the device has not acknowledged them."""
        with self.lock:
            if not self.has_writes or self.outputs is None or self.ack_seq >= self.out_seq:
                return None
            return self.outputs, self.out_seq

    def wait_ack(self, seq: int, until: float) -> bool:
        with self.acked:
            return self.acked.wait_for(
                lambda: self.ack_seq >= seq, timeout=max(0.0, until - time.monotonic())
            )

    def ack(self, seq: int) -> None:
        with self.acked:
            if seq > self.ack_seq:
                self.ack_seq = seq
                self.acked.notify_all()


def no_reply(exc: BaseException) -> bool:
    """A request that got no answer within timeout_s (not a refused connection, not a garbled
    or exception reply): pymodbus 3.16 raises ModbusIOException("No response received ...")
    for it (transaction.py), or TimeoutError."""
    return isinstance(exc, TimeoutError) or (
        isinstance(exc, ModbusIOException) and "No response received" in str(exc))


class IoLink:
    """The I/O thread of one driver; start() runs it, the driver stops it (see close())."""

    def __init__(self, name: str, transport: Transport, plan: IoPlan, state: LinkState) -> None:
        self.name, self.transport, self.plan, self.state = name, transport, plan, state
        self.params = transport.params
        # Thread plumbing; None while closed.
        self.thread: threading.Thread | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._wake = asyncio.Event()
        self._urgent = asyncio.Event()  # cuts a reconnect pause short (go_safe, close)
        # I/O thread only.
        self._fails_on_link = 0
        self._fresh_link = False  # the device's watchdog register is written first
        self._beat = 0
        self._beat_due = 0.0

    def start(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._wake, self._urgent = asyncio.Event(), asyncio.Event()
        self.thread = threading.Thread(
            target=self._thread_main, args=(self.loop,), name=f"modbus-io-{self.name}",
            daemon=True
        )
        self.thread.start()

    def trigger(self, *, urgent: bool = False) -> None:
        """Wake the I/O thread for one cycle; `urgent` also cuts a reconnect pause short."""
        loop = self.loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # closed by close() in another thread
            loop.call_soon_threadsafe(self._wake.set)
            if urgent:
                loop.call_soon_threadsafe(self._urgent.set)

    def stop_loop(self) -> None:
        loop = self.loop
        if loop is not None:
            with contextlib.suppress(RuntimeError):  # the loop has already ended
                loop.call_soon_threadsafe(loop.stop)

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
        with self.state.lock:
            self.state.connected = self.state.last_cycle_ok = False
            self.state.last_error = f"I/O task crashed: {exc!r}"

    async def _run(self) -> None:
        client = self.transport.client(self._on_link)  # reconnection and backoff are ours
        try:
            await self._serve(client)
            await self._flush(client)
        finally:
            client.close()
            self._on_link(False)
            await asyncio.sleep(0)  # let the transport's close callback release the socket

    async def _serve(self, client: Client) -> None:
        p = self.params
        backoff = p.reconnect_min_s
        while not self.state.closing:
            if not client.connected:
                if not await client.connect():
                    self._note_failure(f"cannot connect to {self.transport.where}",
                                       cycle=False)
                    await self._pause(backoff)
                    backoff = min(2 * backoff, p.reconnect_max_s)
                continue
            await self._wake.wait()
            self._wake.clear()
            if self.state.closing or not client.connected:
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
        with self.state.lock:
            if self.state.safe_seq > self.state.ack_seq:
                seconds = min(seconds, self.params.reconnect_min_s)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._urgent.wait(), seconds)
        self._urgent.clear()

    async def _flush(self, client: Client) -> None:
        """On close: the latest outputs, if the device has not acknowledged them."""
        pending = self.state.pending()
        if pending is None:
            return
        try:
            if not client.connected and not await client.connect():
                return
            await self._write_outputs(client, *pending)
        except ERRORS as exc:
            log.warning("modbus driver %s: final write failed: %s", self.name, exc)

    def _on_link(self, connected: bool) -> None:
        with self.state.lock:
            changed = connected != self.state.connected
            self.state.connected, self.state.last_cycle_ok = connected, False
        self._fails_on_link = 0
        self._fresh_link = connected
        if not connected:
            self._wake.set()  # so that _run notices and reconnects
        if changed:
            state = "connected to" if connected else "disconnected from"
            log.info("modbus driver %s: %s %s", self.name, state, self.transport.where)

    async def _cycle(self, client: Client) -> bool:
        shared = self.state
        with shared.lock:
            outputs, seq = shared.outputs, shared.out_seq
        try:
            await self._arm_watchdog(client)
            if outputs is not None:
                await self._write_outputs(client, outputs, seq)
            await self._heartbeat(client)
            inputs = tuple([await read_block(client, b, self.params.unit) for b in self.plan.reads])
        except ERRORS as exc:
            self._fails_on_link += 1
            unanswered = no_reply(exc)
            with shared.lock:
                shared.silent = shared.silent + 1 if unanswered else 0
            self._note_failure(self.transport.silence if unanswered
                               else str(exc) or type(exc).__name__, cycle=True)
            return False
        self._fails_on_link = 0
        with shared.lock:
            shared.inputs = inputs
            shared.ok_seq += 1
            shared.failures = shared.silent = 0
            shared.last_cycle_ok = True
        return True

    async def _write_outputs(self, client: Client, outputs: Outputs,
                             seq: int) -> None:
        """Every write range of `outputs`, then acknowledge `seq`. A safe image handed over
        meanwhile replaces a stale one before its next request goes out."""
        blocks = self.plan.writes
        shared = self.state
        i = 0
        while i < len(blocks):
            with shared.lock:
                if shared.safe_seq > seq:
                    outputs, seq, i = shared.outputs or outputs, shared.out_seq, 0
            await write_block(client, blocks[i], outputs[i], self.params.unit)
            i += 1
        shared.ack(seq)

    async def _arm_watchdog(self, client: Client) -> None:
        beat = self.params.heartbeat
        if not self._fresh_link or beat is None or beat.watchdog_register is None:
            return
        await write_word(client, beat.watchdog_register, beat.watchdog_value or 0,
                         self.params.unit)
        self._fresh_link = False

    async def _heartbeat(self, client: Client) -> None:
        beat = self.params.heartbeat
        now = time.monotonic()
        if beat is None or now < self._beat_due:
            return
        value = (self._beat + 1) & 0xFFFF
        await write_word(client, beat.register, value, self.params.unit)
        self._beat, self._beat_due = value, now + beat.period_ns / 1e9
        with self.state.lock:
            self.state.heartbeats += 1

    def _note_failure(self, error: str, *, cycle: bool) -> None:
        shared = self.state
        with shared.lock:
            first = shared.failures == 0
            shared.failures += 1
            shared.cycles_failed += cycle
            shared.last_cycle_ok = (shared.last_cycle_ok and cycle
                                    and shared.failures < SILENT_AFTER)
            shared.last_error = error
        if first:
            log.warning("modbus driver %s: %s", self.name, error)
