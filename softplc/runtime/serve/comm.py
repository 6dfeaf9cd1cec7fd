"""The service processes: the Modbus TCP slave, the HTTP API and OPC UA, each in its own.

Owns: starting the services a CommConfig turns on against the published snapshot (shared
memory) and the command channel, and stopping them together within STOP_SERVICES_S, then
ending the process at once (the supervisor stops it after the scan's outputs are safe);
how the services are split into processes, at what niceness and scheduler slice
(`service_groups`: one process each, so that no client of one door can delay another beyond
the CPU it is given; docs/design.md section 7); a loop that logs what asyncio reports (an
accept() out of descriptors, ...) at most once per LOOP_LOG_S; which Modbus writes are allowed
(`modbus_writes`: open, the running program's HMI-writable symbols, or none). A crash here
never stops the scan: it is another process.
Does not know: the scan loop's internals, Modbus framing, the register map's layout.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final, Protocol

from softplc.core.image import Address, ImageSizes
from softplc.core.snapshot import HmiWrite, SnapshotSource
from softplc.hmi.admission import Limits
from softplc.hmi.eng import EngSource
from softplc.runtime.serve.timeslice import request_slice
from softplc.runtime.shared.board import StatusBoard
from softplc.runtime.shared.channel import Channel
from softplc.runtime.shared.fresh import FreshSource
from softplc.runtime.shared.procs import Flag as Event
from softplc.runtime.shared.procs import supervisor_pid
from softplc.runtime.shared.shm import SnapshotReader
from softplc.security.writes import WRITE_POLICIES, WritePolicy, locations

if TYPE_CHECKING:
    from softplc.hmi.secure import SecureModbusSlave
    from softplc.hmi.server import ModbusSlave
    from softplc.opcua.limits import OpcUaLimits

log = logging.getLogger("softplc.comm")

# The write policy and the symbol rule every door applies: security/writes.py.
ModbusWrites = WritePolicy
MODBUS_WRITES: Final[tuple[str, ...]] = WRITE_POLICIES
RECHECK_S: Final = 0.001  # one program check per write request, not per written address
# All services stop together, bounded: the supervisor kills what runs 2 s after a signal.
STOP_SERVICES_S: Final = 1.0
# The niceness of each service process, taken once its service serves. The scheduler's
# weights (1024 at nice 0, 526 at 3, 110 at 10) decide who runs when the CPUs are busy:
# Modbus is the HMI's path (polled every cycle, small answers) and yields to the scan only;
# HTTP needs little CPU for stop, status and the page, so a flood of requests there yields
# to Modbus (half its share) and still gets about five times OPC UA's; OPC UA costs the
# most per request (asyncua decodes and encodes in Python) and is served last. Below 0
# needs CAP_SYS_NICE.
MODBUS_NICE: Final = 0
HTTP_NICE: Final = 3
OPCUA_NICE: Final = 10
# The scheduler slice the Modbus process asks for (EEVDF, Linux 6.12+; runtime/serve/timeslice.py).
# It asks to run sooner, not more: its share stays its weight. With the base slice (1.4 ms
# here) a Modbus request arriving while a busy process held the services' CPU (the HTTP
# process refusing a flood of JSON bombs) waited for that process's slice; the woken Modbus
# process now preempts it (PREEMPT_SHORT). Measured (BENCHMARKS.md, Isolation): its wake-up
# delay p99 under the bombs 280-300 -> 100 µs and its p99 response 1.1 -> 0.87 ms when woken
# from the same CPU, 710-770 -> 625-650 µs and 5 % when woken from the other one. 0: the
# base slice (HTTP, OPC UA; Modbus/TCP Security, not measured).
MODBUS_SLICE_NS: Final = 100_000
LOOP_LOG_S: Final = 10.0  # one asyncio error report per this, with the count of the others


@dataclass(frozen=True, slots=True)
class CommConfig:
    modbus: tuple[str, int] | None = ("127.0.0.1", 5020)
    api: tuple[str, int] | None = ("127.0.0.1", 8080)
    state_dir: str = "state"
    sizes: ImageSizes = field(default_factory=ImageSizes)
    modbus_writes: ModbusWrites = "open"
    # Connection slots, per-IP slots, idle timeout (hmi/admission.py, docs/modbus.md).
    modbus_max_connections: int = 16
    modbus_max_per_peer: int = 8
    modbus_idle_timeout_s: float = 60.0
    opcua: tuple[str, int] | None = None  # `softplc run` serves 127.0.0.1:4840 unless told off
    opcua_limits: OpcUaLimits | None = None  # None: the defaults of opcua/limits.py
    modbus_tls: tuple[str, int] | None = None  # Modbus/TCP Security (hmi/secure.py); off
    nice: int = 0  # added to the process's niceness once its services serve
    slice_ns: int = 0  # the scheduler slice asked for once serving; 0: the kernel's base slice

    def __post_init__(self) -> None:
        if self.modbus_writes not in MODBUS_WRITES:
            raise ValueError(f"modbus_writes must be one of {', '.join(MODBUS_WRITES)}, "
                             f"not {self.modbus_writes!r}")
        Limits(self.modbus_max_connections, self.modbus_max_per_peer,
               self.modbus_idle_timeout_s)  # raises ValueError naming the bad one


def service_groups(config: CommConfig) -> dict[str, CommConfig]:
    """The service processes of `config` by name, each with the one service it runs and its
    niceness: "modbus", "modbus-tls", "http", "opcua". A service that is off has no process.
    Each process has its own loop, descriptors and memory: a client that fills one (1,000
    idle OPC UA sockets, a 15 s Read, a flood of JSON bombs) leaves the others answering."""
    off: dict[str, Any] = {"modbus": None, "api": None, "opcua": None, "modbus_tls": None}
    # Modbus/TCP Security in a process of its own: a stranger's TLS handshakes cost CPU that
    # the plain port's HMIs should not share.
    groups = {"modbus": ("modbus", MODBUS_NICE, MODBUS_SLICE_NS),
              "modbus-tls": ("modbus_tls", MODBUS_NICE, 0), "http": ("api", HTTP_NICE, 0),
              "opcua": ("opcua", OPCUA_NICE, 0)}
    return {name: replace(config, **{**off, service: getattr(config, service)}, nice=nice,
                          slice_ns=slice_ns)
            for name, (service, nice, slice_ns) in groups.items()
            if getattr(config, service) is not None}


def modbus_limits(args: Any) -> dict[str, Any]:
    """CommConfig's Modbus connection fields from `softplc run` arguments (cli.py):
    `CommConfig(..., **modbus_limits(args))`."""
    return {"modbus_max_connections": getattr(args, "modbus_max_connections", 16),
            "modbus_max_per_peer": getattr(args, "modbus_max_per_peer", 8),
            "modbus_idle_timeout_s": getattr(args, "modbus_idle_timeout", 60_000_000_000) / 1e9}


class ProgramWritable:
    """The Writable predicate of the policies "symbols" (only the running program's symbols
    that may be written) and "open" (everything but the locations of its symbols declared
    `hmi_writable: false`): follows downloads. The snapshot says which program runs (its
    hash, every scan); the board (refreshed about every 50 ms) lists its symbols. While the
    board still describes another program, nothing is writable: a stale list must not open an
    address of the old program, nor forget one the new program closes."""

    def __init__(self, read_board: Callable[[], dict[str, Any]], source: SnapshotSource,
                 policy: WritePolicy = "symbols") -> None:
        self._read_board = read_board
        self._source = source
        self._open = policy == "open"
        self._program_hash: str | None = None
        self._listed: frozenset[Address] = frozenset()  # writable ("symbols") or closed ("open")
        self._fresh = False
        self._checked_s = float("-inf")

    def __call__(self, address: Address) -> bool:
        listed = address in self._current()
        if not self._fresh:
            return False
        return not listed if self._open else listed

    def _current(self) -> frozenset[Address]:
        now_s = time.monotonic()
        if now_s - self._checked_s < RECHECK_S:
            return self._listed
        self._checked_s = now_s
        running = self._source.latest().status.program_hash
        if not running:  # no program: nothing is declared, so "open" closes nothing
            self._program_hash, self._listed, self._fresh = None, frozenset(), self._open
        elif running != self._program_hash:
            document = self._read_board()
            self._fresh = document.get("program_hash") == running
            self._listed = (locations(document.get("symbols") or {}, writable=not self._open)
                            if self._fresh else frozenset())
            self._program_hash = running if self._fresh else None
        return self._listed


class _Service(Protocol):
    async def stop(self) -> None: ...


def modbus_slave(config: CommConfig, source: SnapshotSource, sink: Callable[[HmiWrite], None],
                 read_board: Callable[[], dict[str, Any]]) -> ModbusSlave:
    """The HMI slave of `config` (not started), with its write policy; its writes audited
    in STATE_DIR's trail (docs/security.md, "Audit of plain Modbus writes")."""
    from softplc.hmi.server import ModbusSlave
    from softplc.hmi.writeaudit import WritesAudited
    from softplc.security.audit import AuditTrail

    if config.modbus is None:
        raise ValueError("Modbus is off in this configuration")
    host, port = config.modbus
    writable = (ProgramWritable(read_board, source, config.modbus_writes)
                if config.modbus_writes != "none" else None)
    audit = WritesAudited(AuditTrail(Path(config.state_dir)), config.modbus_writes)
    return ModbusSlave(source, sink, sizes=config.sizes, host=host, port=port,
                       writable=writable, read_only=config.modbus_writes == "none",
                       max_connections=config.modbus_max_connections,
                       max_per_peer=config.modbus_max_per_peer,
                       idle_timeout_s=config.modbus_idle_timeout_s, audit=audit,
                       presentation=EngSource(read_board, source))


def secure_modbus_slave(config: CommConfig, source: SnapshotSource,
                        sink: Callable[[HmiWrite], None],
                        read_board: Callable[[], dict[str, Any]]) -> SecureModbusSlave:
    """The Modbus/TCP Security slave of `config` (not started): its certificate made at the
    first start in STATE_DIR/modbus-tls/tls/, client certificates trusted in
    STATE_DIR/modbus-tls/trusted/ (docs/modbus.md, Modbus/TCP Security)."""
    from softplc.hmi.secure import MODBUS_TLS_DIR, SecureModbusSlave, TlsConfig
    from softplc.security.audit import AuditTrail
    from softplc.security.tls import TlsSettings, certificate
    from softplc.security.trust import TrustList

    assert config.modbus_tls is not None
    host, port = config.modbus_tls
    state = Path(config.state_dir)
    cert, key, _ = certificate(TlsSettings(), state / MODBUS_TLS_DIR, host)
    tls = TlsConfig(cert, key, TrustList(state, MODBUS_TLS_DIR), AuditTrail(state))
    writable = (ProgramWritable(read_board, source, config.modbus_writes)
                if config.modbus_writes != "none" else None)
    return SecureModbusSlave(source, sink, tls=tls, sizes=config.sizes, host=host, port=port,
                             writable=writable, read_only=config.modbus_writes == "none",
                             max_connections=config.modbus_max_connections,
                             max_per_peer=config.modbus_max_per_peer,
                             idle_timeout_s=config.modbus_idle_timeout_s,
                             presentation=EngSource(read_board, source))


async def _serve(config: CommConfig, channel: Channel, shm_name: str, board_name: str,
                 ready: Event, stop: Event) -> None:
    asyncio.get_running_loop().set_exception_handler(_LoopErrors())
    mapping = SnapshotReader.attach(shm_name, config.sizes)
    reader = FreshSource(mapping)
    board = StatusBoard.attach(board_name)
    services: list[_Service] = []
    if config.modbus is not None:
        slave = modbus_slave(config, reader, channel.send_hmi_write, board.read)
        await slave.start()
        services.append(slave)
    if config.modbus_tls is not None:
        secure = secure_modbus_slave(config, reader, channel.send_hmi_write, board.read)
        await secure.start()
        services.append(secure)
    if config.api is not None:
        from softplc.api.server import ApiServer

        host, port = config.api
        api = ApiServer(channel, reader, board, host=host, port=port,
                        state_dir=Path(config.state_dir))
        await api.start()
        services.append(api)
    if config.opcua is not None:
        services.extend(await _start_opcua(config, channel, reader, board))
    # Only once serving: the start (imports, asyncua's address space) at nice 10 would wait
    # behind any busy process, as the compile process's imports did (compileproc.py: over
    # 10 s beside 4 busy loops).
    if config.nice:
        os.nice(config.nice)
    if config.slice_ns:
        _ask_slice(config.slice_ns)
    ready.set()
    parent = supervisor_pid()
    try:
        while not stop.is_set() and os.getppid() == parent:
            await asyncio.sleep(0.1)
    finally:
        await _stop_services(services)
        mapping.close()
        board.close()


def _ask_slice(slice_ns: int) -> None:
    """The process's scheduler slice; a kernel without custom slices or a refusal (seccomp)
    leaves the base slice, logged once: the service serves either way."""
    answer = request_slice(slice_ns)
    level = logging.INFO if answer.ok else logging.WARNING
    log.log(level, "%s: %s", multiprocessing.current_process().name, answer.words())


async def _stop_services(services: list[_Service]) -> None:
    """Every service at once (each lets its clients go), within STOP_SERVICES_S; one that
    takes longer is logged and abandoned: the process ends next anyway."""
    stops = {asyncio.ensure_future(service.stop()): service for service in services}
    if not stops:
        return
    done, late = await asyncio.wait(stops, timeout=STOP_SERVICES_S)
    for task in late:
        log.warning("%s did not stop within %g s", type(stops[task]).__name__, STOP_SERVICES_S)
        task.cancel()
    for task in done:
        if task.exception() is not None:
            log.error("%s failed to stop: %r", type(stops[task]).__name__, task.exception())


async def _start_opcua(config: CommConfig, channel: Channel, reader: SnapshotSource,
                       board: StatusBoard) -> list[_Service]:
    """The OPC UA server, or none when it cannot start (port taken): Modbus and the API
    keep serving, the failure is logged."""
    from softplc.opcua.server import OpcUaServer

    assert config.opcua is not None
    host, port = config.opcua
    server = OpcUaServer(channel, reader, board, host=host, port=port,
                         state_dir=Path(config.state_dir), modbus_writes=config.modbus_writes,
                         limits=config.opcua_limits)
    try:
        await server.start()
    except Exception:
        log.exception("OPC UA server not started on %s:%d", host, port)
        await server.stop()
        return []
    return [server]


def comm_process_main(config: CommConfig, channel: Channel, shm_name: str, board_name: str,
                      ready: Event, stop: Event) -> None:
    from softplc.runtime.shared.procs import die_with_parent, exit_now, name_process, once

    name_process()  # softplc-http, softplc-modbus, ... (supervisor._TITLES)
    serving = _Serving(ready)

    def on_stop() -> None:
        stop.set()
        if not serving.is_set():  # starting: asyncua's start (seconds) would hold the stop up
            exit_now(0)  # the services already serving close with the process

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, once(on_stop))  # re-entering set() deadlocks (procs.once)
    die_with_parent()
    asyncio.run(_serve(config, channel, shm_name, board_name, serving, stop))
    exit_now(0)  # the services are closed; freeing asyncua's address space took up to 2.4 s


class _Serving(threading.Event):
    """The ready signal to the supervisor, remembered here: a stop before it ends at once."""

    def __init__(self, ready: Event) -> None:
        super().__init__()
        self._ready = ready

    def set(self) -> None:
        super().set()
        self._ready.set()


class _LoopErrors:
    """The loop's exception handler: asyncio's report, at most once per LOOP_LOG_S. Out of
    descriptors, asyncio reported every failed accept() with a traceback (161,395 lines,
    65 MB in 90 s)."""

    def __init__(self) -> None:
        self._next_s = 0.0
        self._skipped = 0

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        now_s = time.monotonic()
        if now_s < self._next_s:
            self._skipped += 1
            return
        if self._skipped:
            context = {**context, "message": f"{context.get('message')} "
                       f"({self._skipped} reports in the last {LOOP_LOG_S:g} s not logged)"}
        self._skipped = 0
        self._next_s = now_s + LOOP_LOG_S
        loop.default_exception_handler(context)
