"""Modbus TCP remote I/O: the PLC is the client, a remote I/O module is the server.

Owns: channel parsing and range planning (pure), the I/O thread with its own asyncio loop and
pymodbus client, the last good inputs, the latest outputs, health and stats.
Does not know: the scan, the Petri net, the HMI slave.

Threading: read_inputs/write_outputs never touch the network; they swap values with the I/O
thread under a lock. write_outputs wakes it for one cycle: every write range, then every read
range, one request each. read_inputs wakes it only if no outputs came since the last read
(first scan, read-only callers). Wake-ups during a cycle coalesce into one more cycle with the
latest outputs. Scan k sees the inputs of the last cycle completed before its read_inputs.

Health: OK when connected and the last cycle succeeded; DEGRADED when connected but the last
cycle failed or none has completed on this connection yet; DOWN when not connected (never,
lost, closed). DROP_AFTER failed cycles in a row (stale for at most that many cycles) drop
the connection; reconnects back off from reconnect_min_s, doubling up to reconnect_max_s."""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import threading
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU

from softplc.core.image import Area, BoolArray, ProcessImage, WordArray
from softplc.core.symbols import DriverSpec, Symbol
from softplc.devices.driver import DeviceError, Health

log = logging.getLogger(__name__)

DROP_AFTER = 3  # failed cycles in a row on one connection before it is dropped
CLOSE_JOIN_S = 1.0
_CANCEL_ROUNDS = 50
MAX_OFFSET = 0xFFFF


class Table(enum.Enum):
    COIL = "coil"
    DI = "di"
    HR = "hr"
    IR = "ir"

    @property
    def is_bit(self) -> bool:
        return self in (Table.COIL, Table.DI)


# Per-request quantity limits of the Modbus application protocol (FC 1/2, 3/4, 15, 16).
_READ_LIMIT = {Table.COIL: 2000, Table.DI: 2000, Table.HR: 125, Table.IR: 125}
_WRITE_LIMIT = {Table.COIL: 1968, Table.HR: 123}
# Where an image location may come from (inputs) or go to (outputs), keyed (area, is_bit).
_ALLOWED = {
    (Area.INPUT, True): (Table.DI, Table.COIL),
    (Area.INPUT, False): (Table.IR, Table.HR),
    (Area.OUTPUT, True): (Table.COIL,),
    (Area.OUTPUT, False): (Table.HR,),
}


@dataclass(frozen=True, slots=True)
class Channel:
    table: Table
    offset: int


def parse_channel(text: str) -> Channel:
    """`di:3` -> Channel(DI, 3). Offsets are 0-based PDU addresses."""
    table_text, sep, offset_text = text.strip().partition(":")
    if not sep:
        raise ValueError(f"channel {text!r}: expected TABLE:OFFSET, e.g. di:0")
    try:
        table = Table(table_text.strip().lower())
    except ValueError:
        raise ValueError(
            f"channel {text!r}: table {table_text!r} is not coil, di, hr or ir"
        ) from None
    try:
        offset = int(offset_text.strip())
    except ValueError:
        raise ValueError(f"channel {text!r}: offset {offset_text!r} is not an integer") from None
    if not 0 <= offset <= MAX_OFFSET:
        raise ValueError(f"channel {text!r}: offset {offset} is not in 0..{MAX_OFFSET}")
    return Channel(table, offset)


@dataclass(frozen=True, slots=True)
class Block:
    """One request per cycle: remote addresses start.. start+count-1, where remote address
    start+i maps to image index image_index[i] (of %IX/%IW for reads, %QX/%QW for writes)."""

    table: Table
    start: int
    image_index: tuple[int, ...]

    @property
    def count(self) -> int:
        return len(self.image_index)

    def __str__(self) -> str:
        return f"{self.table.value}:{self.start}+{self.count}"


@dataclass(frozen=True, slots=True)
class IoPlan:
    reads: tuple[Block, ...]
    writes: tuple[Block, ...]


def plan_channels(symbols: Iterable[Symbol]) -> IoPlan:
    """Validate every symbol's channel and group them into contiguous ranges per table.

    Raises one ValueError listing every problem, each naming the symbol and what was expected.
    """
    used: dict[tuple[Area, Table, int], Symbol] = {}
    issues = [f"symbol {sym.name!r} (line {sym.line}): {issue}"
              for sym, issue in channel_problems(symbols, used)]
    if issues:
        raise ValueError("modbus channels:\n  " + "\n  ".join(issues))
    groups: dict[tuple[Area, Table], list[tuple[int, int]]] = {}
    for (area, table, offset), sym in used.items():
        groups.setdefault((area, table), []).append((offset, sym.address.index))
    return IoPlan(
        _blocks(groups, Area.INPUT, _READ_LIMIT), _blocks(groups, Area.OUTPUT, _WRITE_LIMIT)
    )


def channel_problems(symbols: Iterable[Symbol],
                     used: dict[tuple[Area, Table, int], Symbol] | None = None
                     ) -> list[tuple[Symbol, str]]:
    """Every symbol whose channel this driver would refuse, with why (`softplc check` reports
    them without opening anything). `used` collects the valid channels, for planning."""
    used = {} if used is None else used
    found = ((sym, _check_symbol(sym, used)) for sym in symbols)
    return [(sym, issue) for sym, issue in found if issue]


def _check_symbol(sym: Symbol, used: dict[tuple[Area, Table, int], Symbol]) -> str | None:
    if sym.channel is None:
        return "no channel: expected TABLE:OFFSET with TABLE coil, di, hr or ir"
    try:
        ch = parse_channel(sym.channel)
    except ValueError as exc:
        return str(exc)
    area, is_bit = sym.address.area, sym.address.is_bit
    allowed = _ALLOWED.get((area, is_bit))
    if allowed is None:
        return f"{sym.address} is memory, not I/O: expected an %IX/%IW input or %QX/%QW output"
    if ch.table not in allowed:
        role = "input" if area is Area.INPUT else "output"
        kind = "bit" if is_bit else "word"
        names = " or ".join(t.value for t in allowed)
        return f"channel {sym.channel!r}: a {kind} {role} ({sym.address}) expects {names}"
    key = (area, ch.table, ch.offset)
    if key in used:
        return f"channel {sym.channel!r} is already used by symbol {used[key].name!r}"
    used[key] = sym
    return None


def _blocks(
    groups: Mapping[tuple[Area, Table], list[tuple[int, int]]],
    area: Area,
    limits: Mapping[Table, int],
) -> tuple[Block, ...]:
    out: list[Block] = []
    for (group_area, table), pairs in sorted(groups.items(), key=lambda kv: kv[0][1].value):
        if group_area is not area:
            continue
        run: list[tuple[int, int]] = []
        for offset, index in sorted(pairs):
            if run and (offset != run[-1][0] + 1 or len(run) == limits[table]):
                out.append(Block(table, run[0][0], tuple(i for _, i in run)))
                run = []
            run.append((offset, index))
        out.append(Block(table, run[0][0], tuple(i for _, i in run)))
    return tuple(out)


@dataclass(frozen=True, slots=True)
class ModbusParams:
    host: str
    port: int
    unit: int = 1
    timeout_s: float = 0.2
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    poll: str = "scan"

    @classmethod
    def from_spec(cls, spec: DriverSpec) -> ModbusParams:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(spec.params) - known)
        if unknown:
            raise ValueError(
                f"driver {spec.name!r}: unknown params {unknown}, expected {sorted(known)}"
            )
        if "host" not in spec.params or "port" not in spec.params:
            raise ValueError(f"driver {spec.name!r}: params host and port are required")
        params = cls(**dict(spec.params))
        problem = params._problem()
        if problem:
            raise ValueError(f"driver {spec.name!r}: {problem}")
        return params

    def _problem(self) -> str | None:
        checks = (
            (isinstance(self.host, str) and bool(self.host), "host must be a non-empty string"),
            (_is_int(self.port) and 1 <= self.port <= 65535, "port must be an integer in 1..65535"),
            (_is_int(self.unit) and 0 <= self.unit <= 255, "unit must be an integer in 0..255"),
            (_positive(self.timeout_s), "timeout_s must be a positive number"),
            (_positive(self.reconnect_min_s), "reconnect_min_s must be a positive number"),
            (
                _positive(self.reconnect_max_s) and self.reconnect_max_s >= self.reconnect_min_s,
                "reconnect_max_s must be a number >= reconnect_min_s",
            ),
            (self.poll == "scan", f"poll {self.poll!r}: only 'scan' (one cycle per scan) exists"),
        )
        return next((msg for ok, msg in checks if not ok), None)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _positive(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and value > 0


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


class RemoteError(DeviceError):
    """The remote device answered a request with a Modbus exception or a short reply."""


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
        self.params = ModbusParams.from_spec(spec)
        self.plan = plan_channels(symbols)
        self._read_index = [np.array(b.image_index, dtype=np.intp) for b in self.plan.reads]
        self._write_index = [np.array(b.image_index, dtype=np.intp) for b in self.plan.writes]
        self._lock = threading.Lock()
        # Written by the I/O thread, read by the scan thread; under _lock.
        self._inputs: tuple[BoolArray | WordArray, ...] | None = None
        self._ok_seq = 0
        self._cycles_failed = 0
        self._failures = 0
        self._connected = False
        self._last_cycle_ok = False
        self._last_error = ""
        # Written by the scan thread; _outputs also read by the I/O thread under _lock.
        self._outputs: tuple[list[Any], ...] | None = None
        self._seen_seq = 0
        self._last_ok_ns: int | None = None
        self._stale_scans = 0
        self._wrote_since_read = False
        # I/O thread plumbing; None while closed.
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake = asyncio.Event()
        self._fails_on_link = 0  # I/O thread only

    # ----- scan side -----

    def open(self) -> None:
        if self._thread is not None:
            return
        _quiet_pymodbus()
        self._loop = asyncio.new_event_loop()
        self._wake = asyncio.Event()
        self._thread = threading.Thread(
            target=self._thread_main, args=(self._loop,), name=f"modbus-io-{self.name}", daemon=True
        )
        self._thread.start()

    def close(self) -> None:
        thread, loop = self._thread, self._loop
        if thread is None or loop is None:
            return
        self._thread = self._loop = None
        with contextlib.suppress(RuntimeError):  # the loop has already ended
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=CLOSE_JOIN_S)
        if thread.is_alive():
            log.warning(
                "modbus driver %s: I/O thread did not stop within %ss", self.name, CLOSE_JOIN_S
            )
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
        outputs = tuple(
            (image.qx if block.table.is_bit else image.qw)[index].tolist()
            for block, index in zip(self.plan.writes, self._write_index, strict=True)
        )
        with self._lock:
            self._outputs = outputs
        self._wrote_since_read = True
        self._trigger()

    def health(self) -> Health:
        if self._thread is None:
            return Health.DOWN
        with self._lock:
            return _HEALTH.get((self._connected, self._last_cycle_ok), Health.DOWN)

    def problem(self) -> str:
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
            )

    def _trigger(self) -> None:
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # closed by close() in another thread
            loop.call_soon_threadsafe(self._wake.set)

    # ----- I/O thread -----

    def _thread_main(self, loop: asyncio.AbstractEventLoop) -> None:
        asyncio.set_event_loop(loop)
        task = loop.create_task(self._run())
        task.add_done_callback(self._on_run_done)
        try:
            loop.run_forever()
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
        backoff = p.reconnect_min_s
        try:
            while True:
                if not client.connected:
                    if not await client.connect():
                        self._note_failure(f"cannot connect to {p.host}:{p.port}", cycle=False)
                        await asyncio.sleep(backoff)
                        backoff = min(2 * backoff, p.reconnect_max_s)
                    continue
                await self._wake.wait()
                self._wake.clear()
                if not client.connected:
                    continue
                if await self._cycle(client):
                    backoff = p.reconnect_min_s
                elif self._fails_on_link >= DROP_AFTER:
                    log.warning("modbus driver %s: dropping the connection", self.name)
                    client.close()  # a closing client reports no disconnect: do it here
                    self._on_link(False)
                    await asyncio.sleep(backoff)
                    backoff = min(2 * backoff, p.reconnect_max_s)
        finally:
            client.close()
            self._on_link(False)
            await asyncio.sleep(0)  # let the transport's close callback release the socket

    def _on_link(self, connected: bool) -> None:
        with self._lock:
            changed = connected != self._connected
            self._connected, self._last_cycle_ok = connected, False
        self._fails_on_link = 0
        if not connected:
            self._wake.set()  # so that _run notices and reconnects
        if changed:
            p = self.params
            state = "connected to" if connected else "disconnected from"
            log.info("modbus driver %s: %s %s:%s", self.name, state, p.host, p.port)

    async def _cycle(self, client: AsyncModbusTcpClient) -> bool:
        with self._lock:
            outputs = self._outputs
        try:
            if outputs is not None:
                for block, values in zip(self.plan.writes, outputs, strict=True):
                    await self._write(client, block, values)
            inputs = tuple([await self._read(client, block) for block in self.plan.reads])
        except (TimeoutError, ModbusException, DeviceError, OSError) as exc:
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

    def _note_failure(self, error: str, *, cycle: bool) -> None:
        with self._lock:
            first = self._failures == 0
            self._failures += 1
            self._cycles_failed += cycle
            self._last_cycle_ok = False
            self._last_error = error
        if first:
            log.warning("modbus driver %s: %s", self.name, error)

    async def _read(self, client: AsyncModbusTcpClient, block: Block) -> BoolArray | WordArray:
        request = {
            Table.COIL: client.read_coils,
            Table.DI: client.read_discrete_inputs,
            Table.HR: client.read_holding_registers,
            Table.IR: client.read_input_registers,
        }[block.table]
        reply = _checked(
            await request(block.start, count=block.count, device_id=self.params.unit), block
        )
        values = reply.bits if block.table.is_bit else reply.registers
        if len(values) < block.count:
            raise RemoteError(f"{block}: short reply ({len(values)} values)")
        dtype: npt.DTypeLike = np.bool_ if block.table.is_bit else np.uint16
        return np.asarray(values[: block.count], dtype=dtype)

    async def _write(self, client: AsyncModbusTcpClient, block: Block, values: list[Any]) -> None:
        unit = self.params.unit
        if block.table is Table.COIL:
            reply = await client.write_coils(block.start, values, device_id=unit)
        else:
            reply = await client.write_registers(block.start, values, device_id=unit)
        _checked(reply, block)


def _checked(reply: ModbusPDU, block: Block) -> ModbusPDU:
    if reply.isError():
        raise RemoteError(f"{block}: Modbus exception code {reply.exception_code}")
    return reply


def _quiet_pymodbus() -> None:
    """pymodbus logs warnings and errors with frame dumps on every failed (re)connect and
    timeout; our own logger reports state changes once. An explicitly set level is kept."""
    logger = logging.getLogger("pymodbus")
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.CRITICAL)
