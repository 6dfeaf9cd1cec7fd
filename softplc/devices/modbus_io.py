"""Modbus remote I/O: the PLC is the client (master), a remote I/O module is the server.

Owns: the driver the scan calls (read_inputs, write_outputs, go_safe: a confirmed write
within a bound, health and stats). The I/O thread (its asyncio loop and pymodbus client, the
heartbeat that keeps the device's own watchdog alive) and the state it shares with the scan
thread are modbus_link.py; channel planning is modbus_plan.py, params modbus_params.py, the
requests themselves modbus_requests.py, the wire (TCP here, RTU in modbus_rtu.py)
modbus_transport.py. 32/64-bit symbols move as 2/4 registers in the device's word order
(modbus_plan.py), each value in one request (FC3/FC4 reads, FC16 writes).
Does not know: the scan, the Petri net, the HMI.

Threading: read_inputs/write_outputs never touch the network; they swap values with the I/O
thread under a lock. write_outputs wakes it for one cycle: every write range, the heartbeat
when due, then every read range, one request each. read_inputs wakes it only if no outputs
came since the last read (first scan, read-only callers). Wake-ups during a cycle coalesce
into one more cycle with the latest outputs. Scan k sees the inputs of the last cycle
completed before its read_inputs. Each output image handed over has a sequence number; the
I/O thread acknowledges the number once the device has answered every write of it.

go_safe hands over the safe image, cuts short any reconnect backoff and waits for its
acknowledgement, unless the device has stopped answering (SILENT_AFTER cycles in a row without
a reply: the scan would only wait out its timeout; the I/O thread writes the safe image when it
answers again, and go_safe says it is not confirmed); if the I/O thread has not confirmed
within half the bound (wedged, dead, closed), it writes on a fresh connection of its own within
the rest. close() lets the I/O thread flush the latest unacknowledged outputs before it ends,
and writes them directly if the thread cannot: a stop never drops the safe write.

Health: OK when connected and the last cycle succeeded (or, after a good one, only the last
failed: SILENT_AFTER in modbus_link.py); DEGRADED when connected but SILENT_AFTER cycles in a
row failed or none has completed on this connection yet; DOWN when not connected (never,
lost, closed). DROP_AFTER failed cycles in a row (stale for at most that many cycles) drop
the connection; reconnects back off from reconnect_min_s, doubling up to reconnect_max_s."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from softplc.core.image import ProcessImage
from softplc.core.symbols import DriverSpec, Symbol
from softplc.devices.driver import Health
from softplc.devices.modbus_link import DROP_AFTER, SILENT_AFTER, IoLink, LinkState, Outputs
from softplc.devices.modbus_params import Heartbeat, ModbusParams
from softplc.devices.modbus_plan import (
    MAX_OFFSET,
    Block,
    Channel,
    IoPlan,
    Table,
    WordOrder,
    channel_problems,
    join_words,
    parse_channel,
    plan_channels,
    split_words,
)
from softplc.devices.modbus_requests import RemoteError, quiet_pymodbus
from softplc.devices.modbus_transport import TCP, Wire

__all__ = [
    "DROP_AFTER", "MAX_OFFSET", "Block", "Channel", "Heartbeat", "IoPlan", "IoStats",
    "ModbusIoDriver", "ModbusParams", "RemoteError", "Table", "WordOrder", "channel_problems",
    "parse_channel", "plan_channels",
]

log = logging.getLogger(__name__)

CLOSE_JOIN_S = 1.0  # the I/O thread's time to flush and end on close()
CLOSE_DIRECT_S = 0.5  # then, if it could not, a direct write of the pending outputs
THREAD_SHARE = 0.5  # of go_safe's bound, for the I/O thread before the direct write


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

    def __init__(self, spec: DriverSpec, symbols: Sequence[Symbol], wire: Wire = TCP) -> None:
        if spec.kind != wire.kind:
            raise ValueError(f"driver {spec.name!r}: kind {spec.kind!r}, expected {wire.kind!r}")
        foreign = [s.name for s in symbols if s.driver != spec.name]
        if foreign:
            raise ValueError(f"driver {spec.name!r}: symbols {foreign} belong to another driver")
        self.name = spec.name
        self.spec = spec  # what the runtime opened, for the start-up gate (docs/faults.md)
        self.plan = plan_channels(symbols)
        self.transport = wire.transport(spec, self.plan)
        self.params = self.transport.params
        self._read_index = [np.array(b.image_index, dtype=np.intp) for b in self.plan.reads]
        self._write_index = [np.array(b.image_index, dtype=np.intp) for b in self.plan.writes]
        self._order = WordOrder(self.params.word_order)
        # The image arrays by attribute name ("ix", "iw", "id", "il"; "qx", ...): each block's.
        self._read_attr = ["i" + b.area_width.lower() for b in self.plan.reads]
        self._write_attr = ["q" + b.area_width.lower() for b in self.plan.writes]
        self._shared = LinkState(has_writes=bool(self.plan.writes))
        self._link = IoLink(self.name, self.transport, self.plan, self._shared)
        # Scan thread only.
        self._seen_seq = 0
        self._last_ok_ns: int | None = None
        self._stale_scans = 0
        self._wrote_since_read = False
        self._delivered = False  # read_inputs copied one completed cycle's inputs since open()

    @property
    def _loop(self) -> asyncio.AbstractEventLoop | None:
        """The I/O thread's loop (None while closed)."""
        return self._link.loop

    def open(self) -> None:
        if self._link.thread is not None:
            return
        quiet_pymodbus()
        with self._shared.lock:  # inputs of an earlier opening are not this one's first image
            self._shared.closing, self._shared.inputs = False, None
            self._shared.silent = 0
        self._delivered = False
        self.transport.attach()
        self._link.start()

    def close(self) -> None:
        """Stop the I/O thread, after it wrote the latest outputs if the device had not yet
        acknowledged them; if it cannot within CLOSE_JOIN_S, write them directly. With nothing
        to write, the thread is stopped at once (a close never waits for a connect)."""
        link, shared = self._link, self._shared
        thread = link.thread
        if thread is None or link.loop is None:
            return
        with shared.lock:
            shared.closing = True
        if shared.pending() is None:  # nothing to flush: do not wait for a connect under way
            link.stop_loop()
        else:
            link.trigger(urgent=True)
        thread.join(timeout=CLOSE_JOIN_S)
        if thread.is_alive():
            link.stop_loop()
            log.warning(
                "modbus driver %s: I/O thread did not stop within %ss", self.name, CLOSE_JOIN_S
            )
        link.thread = link.loop = None
        pending = shared.pending()
        if pending is not None:
            self._direct(*pending, time.monotonic() + CLOSE_DIRECT_S)
        with shared.lock:
            shared.connected = shared.last_cycle_ok = False
        self.transport.detach()

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        with self._shared.lock:
            inputs, seq = self._shared.inputs, self._shared.ok_seq
        # Wake the I/O thread only after the copy: scan k must not see a cycle it started.
        if not self._wrote_since_read:
            self._link.trigger()
        self._wrote_since_read = False
        if seq != self._seen_seq:
            self._seen_seq, self._last_ok_ns, self._stale_scans = seq, now_ns, 0
        else:
            self._stale_scans += 1
        if inputs is None:
            return
        for block, attr, index, values in zip(self.plan.reads, self._read_attr,
                                              self._read_index, inputs, strict=True):
            getattr(image, attr)[index] = (values if block.words == 1
                                           else join_words(values, block.words, self._order))
        self._delivered = True

    def delivered(self) -> bool:
        """Has read_inputs copied the inputs of one completed cycle since open()? Health alone
        cannot say: a cycle may complete between this scan's copy and its health() call."""
        return self._delivered

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        self._hand_over(image, safe=False)
        self._wrote_since_read = True
        self._link.trigger()

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool:
        """Write the outputs of `image` and wait for the device's acknowledgement, at most
        timeout_s. Replaces any queued outputs; see the module docstring for the fallback."""
        deadline = time.monotonic() + timeout_s
        outputs, seq = self._hand_over(image, safe=True)
        if not self.plan.writes:
            return self._safe_result(True, "")
        thread = self._link.thread
        if thread is not None and thread.is_alive():
            self._link.trigger(urgent=True)
            with self._shared.lock:
                silent = self._shared.silent >= SILENT_AFTER
            if silent:  # waiting would only stall the scan: the thread writes them on answer
                return self._safe_result(False, f"{self.transport.silence} (queued: written "
                                                "when it answers)")
            if self._shared.wait_ack(seq, time.monotonic() + timeout_s * THREAD_SHARE):
                return self._safe_result(True, "")
        why = self._direct(outputs, seq, deadline)
        confirmed = self._shared.wait_ack(seq, time.monotonic())  # the thread may have made it
        return self._safe_result(confirmed, "" if confirmed else why)

    def health(self) -> Health:
        if self._link.thread is None:
            return Health.DOWN
        with self._shared.lock:
            return _HEALTH.get((self._shared.connected, self._shared.last_cycle_ok), Health.DOWN)

    def problem(self) -> str:
        shared = self._shared
        with shared.lock:
            if shared.safe_error:
                return shared.safe_error
        if self._link.thread is None:
            return "closed"
        with shared.lock:
            if shared.connected and shared.last_cycle_ok:
                return ""
            if shared.last_error:
                return shared.last_error
            where = self.transport.where
            return "no cycle completed yet" if shared.connected else f"not connected to {where}"

    def stats(self) -> IoStats:
        shared = self._shared
        with shared.lock:
            return IoStats(
                connected=shared.connected,
                last_ok_ns=self._last_ok_ns,
                consecutive_failures=shared.failures,
                stale_scans=self._stale_scans,
                cycles_ok=shared.ok_seq,
                cycles_failed=shared.cycles_failed,
                last_error=shared.last_error,
                heartbeats=shared.heartbeats,
            )

    def _hand_over(self, image: ProcessImage, *, safe: bool) -> tuple[Outputs, int]:
        outputs = tuple(
            getattr(image, attr)[index].tolist() if block.words == 1
            else split_words(getattr(image, attr)[index], block.words, self._order)
            for block, attr, index in zip(self.plan.writes, self._write_attr,
                                          self._write_index, strict=True)
        )
        shared = self._shared
        with shared.lock:
            shared.out_seq += 1
            shared.outputs = outputs
            if safe:
                shared.safe_seq = shared.out_seq
            return outputs, shared.out_seq

    def _safe_result(self, confirmed: bool, why: str) -> bool:
        with self._shared.lock:
            self._shared.safe_error = "" if confirmed else f"safe outputs not confirmed: {why}"
        return confirmed

    def _direct(self, outputs: Outputs, seq: int, deadline: float) -> str:
        """Write `outputs` on a fresh connection of our own (the I/O thread's may be wedged)
        within `deadline`; acknowledge `seq` when the device answered. "" or why not."""
        why = self.transport.write_direct(self.plan.writes, outputs, deadline)
        if not why:
            self._shared.ack(seq)
        return why
