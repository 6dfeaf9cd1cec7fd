"""Stop paths with every service on and a client on each: outputs safe first, then the rest.

A real `softplc run` (supervisor, scan, communication and compile processes) with Modbus,
the HTTP API and OPC UA all serving, drives a lamp on a remote-I/O module: a stdlib Modbus
TCP server in this process on port 0 that timestamps every write it confirms, and takes
WRITE_LATENCY_S to confirm one that changes a coil (a slow fieldbus; then a service stopped
beside the scan, not after it, visibly lets its clients go first). Clients stay
attached while it stops: an OPC UA session with a subscription, an HTTP event stream
(/api/v1/events) and a Modbus connection. docs/operations.md promises, measured from the
request: the lamp's coil written 0 and confirmed within 500 ms, before any service lets its
clients go; for SIGTERM and SIGINT every process of the group gone within 2 s, also when the
signal comes while the services are still starting (OPC UA takes seconds to start);
`softplc stop` leaves the processes serving. Every wait is bounded; the process group is
killed at the end whatever happened.
"""

from __future__ import annotations

import asyncio
import contextlib
import http.client
import os
import signal
import socket
import socketserver
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from asyncua import ua
from asyncua.client.ua_client import UASocketState

from softplc.cli import build_parser
from softplc.cli import main as cli_main
from tests.opcua.conftest import patient_client
from tests.support import eventually, free_port

ROOT = Path(__file__).resolve().parents[2]
SAFE_S = 0.5  # docs/operations.md: safe outputs, confirmed by the device, within 500 ms
GONE_S = 2.0  # docs/operations.md: SIGTERM/SIGINT: every process gone within 2 s
WRITE_LATENCY_S = 0.15
START_S = 90.0  # spawning three processes and asyncua's start take seconds on a loaded box

IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: 1.0,
         reconnect_min_s: 0.05, reconnect_max_s: 0.5}}
symbols:
  lamp: {{address: "%QX0.0", channel: "coil:0"}}
"""
PROGRAM = """\
program: lamp
io_image: io.yaml
places:
  on: {tokens: 1, outputs: [lamp]}
"""


class RemoteIo(socketserver.ThreadingTCPServer):
    """A Modbus TCP remote-I/O module (function codes 1-6, 15, 16; 64 of each table) that
    records when it confirmed each coil write: (time.monotonic(), first coil, values)."""

    daemon_threads = True
    allow_reuse_address = True

    def __init__(self) -> None:
        super().__init__(("127.0.0.1", 0), _ModbusHandler)
        self.coils = [False] * 64
        self.registers = [0] * 64
        self.coil_writes: list[tuple[float, int, list[bool]]] = []
        # Every request: (time.monotonic() received, answered, connection, function code);
        # a failed bound prints the ones after the request, so it says where the time went.
        self.requests: list[tuple[float, float, int, int]] = []
        self.lock = threading.Lock()
        threading.Thread(target=self.serve_forever, args=(0.05,), daemon=True).start()

    @property
    def port(self) -> int:
        return int(self.server_address[1])

    def lamp(self) -> bool:
        with self.lock:
            return self.coils[0]

    def safe_at(self, since: float) -> float | None:
        """When coil 0 was first written 0 at or after `since`."""
        with self.lock:
            return next((t for t, first, values in self.coil_writes
                         if t >= since and first == 0 and not values[0]), None)

    def requests_since(self, since: float) -> str:
        """The requests received from `since` on, one line each, times in ms from it."""
        with self.lock:
            return "\n".join(
                f"  fc {fc} on connection {conn}: received {(got - since) * 1000:.0f} ms, "
                f"answered {(done - since) * 1000:.0f} ms"
                for got, done, conn, fc in self.requests if done >= since)

    def changes_a_coil(self, pdu: bytes) -> bool:
        """Whether `pdu` writes coil 0 (the lamp) to another value than it has."""
        if pdu[0] not in (5, 15) or pdu[1:3] != b"\0\0":
            return False
        on = pdu[3:5] == b"\xff\0" if pdu[0] == 5 else bool(pdu[6] & 1)
        return on != self.lamp()

    def answer(self, pdu: bytes) -> bytes:
        fc = pdu[0]
        start, count = struct.unpack(">HH", pdu[1:5])
        with self.lock:
            if fc in (1, 2):
                bits = self.coils[start:start + count] if fc == 1 else [False] * count
                packed = bytes(sum(1 << i for i, on in enumerate(bits[n:n + 8]) if on)
                               for n in range(0, count, 8))
                return bytes((fc, len(packed))) + packed
            if fc in (3, 4):
                words = self.registers[start:start + count]
                return bytes((fc, 2 * count)) + struct.pack(f">{count}H", *words)
            if fc == 5:
                self._write_coils(start, [count == 0xFF00])
                return pdu[:5]
            if fc == 6:
                self.registers[start] = count
                return pdu[:5]
            if fc == 15:
                data = pdu[6:]
                self._write_coils(start, [bool(data[i // 8] >> (i % 8) & 1)
                                          for i in range(count)])
                return pdu[:5]
            if fc == 16:
                self.registers[start:start + count] = struct.unpack(f">{count}H", pdu[6:])
                return pdu[:5]
        return bytes((fc | 0x80, 1))

    def _write_coils(self, start: int, values: list[bool]) -> None:
        self.coils[start:start + len(values)] = values
        self.coil_writes.append((time.monotonic(), start, values))


class _ModbusHandler(socketserver.BaseRequestHandler):
    server: RemoteIo

    def handle(self) -> None:
        with contextlib.suppress(OSError):
            while header := _read_exactly(self.request, 7):
                tid, _, length, unit = struct.unpack(">HHHB", header)
                pdu = _read_exactly(self.request, length - 1)
                if not pdu:
                    return
                received = time.monotonic()
                if self.server.changes_a_coil(pdu):
                    time.sleep(WRITE_LATENCY_S)
                reply = self.server.answer(pdu)
                with self.server.lock:
                    self.server.requests.append(
                        (received, time.monotonic(), self.request.fileno(), pdu[0]))
                self.request.sendall(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)


def _read_exactly(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            return b""
        data += chunk
    return data


@dataclass
class Clients:
    """One client per service; each records when its service let it go (EOF, reset). `done`
    is set by close(): an ending after it is the test's own."""

    lost: dict[str, float] = field(default_factory=dict)
    done: threading.Event = field(default_factory=threading.Event)
    _threads: list[threading.Thread] = field(default_factory=list)
    closers: list[Callable[[], None]] = field(default_factory=list)

    def watch(self, name: str, target: Callable[[], None]) -> None:
        def run() -> None:
            with contextlib.suppress(Exception):  # any ending is a lost connection
                target()
            if not self.done.is_set():
                self.lost.setdefault(name, time.monotonic())

        thread = threading.Thread(target=run, name=f"client-{name}", daemon=True)
        thread.start()
        self._threads.append(thread)

    def close(self) -> None:
        self.done.set()
        for closer in self.closers:
            with contextlib.suppress(OSError):
                closer()
        for thread in self._threads:
            thread.join(5)


def attach_modbus(clients: Clients, port: int) -> None:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.sendall(struct.pack(">HHHBBHH", 1, 0, 6, 1, 3, 0, 1))  # read holding register 0
    assert len(_read_exactly(sock, 11)) == 11, "the Modbus slave did not answer"
    sock.settimeout(0.2)

    def until_eof() -> None:
        with sock:
            while not clients.done.is_set():
                with contextlib.suppress(TimeoutError):
                    if not sock.recv(64):
                        return

    clients.watch("modbus", until_eof)


def attach_events(clients: Clients, port: int) -> None:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    connection.request("GET", "/api/v1/events")
    response = connection.getresponse()
    assert response.status == 200, response.read()

    def until_eof() -> None:
        with contextlib.closing(connection):
            while not clients.done.is_set() and response.readline():
                pass

    sock = connection.sock
    assert sock is not None
    clients.closers.append(lambda: sock.shutdown(socket.SHUT_RDWR))
    clients.watch("http events", until_eof)


def attach_opcua(clients: Clients, port: int) -> None:
    subscribed = threading.Event()

    class Quiet:
        def datachange_notification(self, node: object, value: object, data: object) -> None:
            pass

        def status_change_notification(self, status: object) -> None:
            pass

    async def session() -> None:
        client = patient_client(f"opc.tcp://127.0.0.1:{port}", 10)
        await client.connect()
        try:
            subscription = await client.create_subscription(50, Quiet())
            await subscription.subscribe_data_change(
                client.get_node(ua.ObjectIds.Server_ServerStatus_CurrentTime))
            subscribed.set()
            protocol = client.uaclient.protocol
            while protocol is not None and protocol.state is not UASocketState.CLOSED:
                if clients.done.is_set():
                    return
                await asyncio.sleep(0.005)
            clients.lost.setdefault("opcua", time.monotonic())  # not after the disconnect
        finally:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.disconnect(), 2)

    clients.watch("opcua", lambda: asyncio.run(session()))
    assert subscribed.wait(30), "no OPC UA session with a subscription"


@dataclass
class Plc:
    proc: subprocess.Popen[str]
    device: RemoteIo
    ports: dict[str, int]
    lines: list[str]

    def story(self, since: float) -> str:
        """What the device was asked from `since` on, and what the PLC said last."""
        return (f"device requests:\n{self.device.requests_since(since)}\nthe PLC said:\n"
                + "".join(self.lines[-15:]))

    def said(self, text: str) -> bool:
        return any(text in line for line in list(self.lines))

    def group(self) -> list[int]:
        """The live (not zombie) processes of its process group."""
        return [pid for pid, pgrp, state in _processes()
                if pgrp == self.proc.pid and state != "Z"]


def _processes() -> Iterator[tuple[int, int, str]]:
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError, IndexError, ValueError):
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                yield int(entry.name), int(fields[2]), fields[0]


@pytest.fixture
def start_plc(tmp_path: Path) -> Iterator[Callable[[], Plc]]:
    device = RemoteIo()
    started: list[Plc] = []

    def start() -> Plc:
        (tmp_path / "io.yaml").write_text(IO.format(port=device.port), encoding="utf-8")
        (tmp_path / "lamp.yaml").write_text(PROGRAM, encoding="utf-8")
        ports = {"modbus": free_port(), "api": free_port(), "opcua": free_port()}
        proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", str(tmp_path / "lamp.yaml"), "--start",
             "--quiet", "--state-dir", str(tmp_path / "state"), "--period", "10ms",
             # processes, not cycle timing: a loaded machine must not fault the lamp off
             "--watchdog", "100", "--on-stall", "continue",
             *(arg for name, port in ports.items()
               for arg in (f"--{name}", f"127.0.0.1:{port}"))],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True)
        lines: list[str] = []

        def read() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                lines.append(line)

        threading.Thread(target=read, daemon=True).start()
        plc = Plc(proc, device, ports, lines)
        started.append(plc)
        eventually(device.lamp, START_S, "the lamp on", step_s=0.005,
                   show=lambda: "".join(lines[-20:]))
        return plc

    yield start
    for plc in started:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(plc.proc.pid, signal.SIGKILL)
        plc.proc.wait(10)
    device.shutdown()
    device.server_close()


def serving(plc: Plc) -> Clients:
    """Wait until `softplc run` serves everything, then attach one client to each service."""
    eventually(lambda: plc.said("supervisor pid"), START_S, "the banner",
               show=lambda: "".join(plc.lines[-20:]))
    clients = Clients()
    attach_opcua(clients, plc.ports["opcua"])
    attach_events(clients, plc.ports["api"])
    attach_modbus(clients, plc.ports["modbus"])
    assert plc.device.lamp() and not clients.lost, clients.lost
    return clients


def gone_after(plc: Plc, since: float, limit_s: float = 10.0) -> float:
    """Seconds from `since` until no process of the group lives (inf after limit_s); prints
    when each ended (shown with pytest -s)."""
    alive = {pid: _name(pid) for pid in plc.group()}
    while alive:
        now = time.monotonic()
        for pid in set(alive) - set(plc.group()):
            print(f"  {alive.pop(pid)} ended after {(now - since) * 1000:.0f} ms")
        if now - since > limit_s:
            return float("inf")
        time.sleep(0.01)
    return time.monotonic() - since


def _name(pid: int) -> str:
    with contextlib.suppress(OSError):
        words = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
        return f"{pid} " + next((w for w in words if "resource_tracker" in w or "pipe_handle" in w
                                 or w == "run"), words[0])[:60]
    return str(pid)


def safe_after(plc: Plc, since: float, limit_s: float = 5.0) -> float:
    """Seconds from `since` until the device confirmed the lamp's coil 0 (inf after limit_s)."""
    while (at := plc.device.safe_at(since)) is None:
        if time.monotonic() - since > limit_s:
            return float("inf")
        time.sleep(0.005)
    return at - since


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_makes_outputs_safe_first_then_ends_every_process(
        start_plc: Callable[[], Plc], sig: signal.Signals) -> None:
    plc = start_plc()
    clients = serving(plc)
    try:
        t0 = time.monotonic()
        plc.proc.send_signal(sig)
        safe = safe_after(plc, t0)
        gone = gone_after(plc, t0)
    finally:
        clients.close()
    lost = {name: at - t0 for name, at in clients.lost.items()}
    print(f"{sig.name}: safe after {safe * 1000:.0f} ms, group gone after {gone * 1000:.0f} ms, "
          f"clients let go after {({k: round(v * 1000) for k, v in lost.items()})} ms")
    assert safe < SAFE_S, f"lamp still on {safe:.2f} s after {sig.name}\n{plc.story(t0)}"
    assert all(at >= safe for at in lost.values()), (
        f"a service let its client go before the outputs were safe ({safe:.3f} s): {lost}")
    assert gone < GONE_S, f"processes still alive {gone:.2f} s after {sig.name}"
    assert plc.proc.wait(5) == 0
    assert plc.said("outputs safe"), "".join(plc.lines)


def test_a_signal_while_the_services_start_is_not_held_up_by_them(
        start_plc: Callable[[], Plc]) -> None:
    plc = start_plc()  # the lamp is on: the scan runs, the services may still be starting
    t0 = time.monotonic()
    plc.proc.send_signal(signal.SIGTERM)
    safe = safe_after(plc, t0)
    gone = gone_after(plc, t0)
    print(f"SIGTERM while starting: safe after {safe * 1000:.0f} ms, "
          f"group gone after {gone * 1000:.0f} ms")
    assert safe < SAFE_S, f"lamp still on {safe:.2f} s after SIGTERM\n{plc.story(t0)}"
    assert gone < GONE_S, f"processes still alive {gone:.2f} s after SIGTERM"
    assert plc.proc.wait(5) == 0


def test_softplc_stop_makes_outputs_safe_and_everything_keeps_serving(
        start_plc: Callable[[], Plc]) -> None:
    plc = start_plc()
    clients = serving(plc)
    try:
        # The bound is from the request: the CLI's imports (its parser imports every command's
        # module, 0.7 s beside 8 busy loops when no bytecode is cached) done before t0, as
        # the interpreter's start is not counted either (the command runs in this process).
        build_parser()
        t0 = time.monotonic()
        code = cli_main(["stop", "--api", f"http://127.0.0.1:{plc.ports['api']}"])
        safe = safe_after(plc, t0)
        print(f"softplc stop: safe after {safe * 1000:.0f} ms")
        assert code == 0
        assert safe < SAFE_S, f"lamp still on {safe:.2f} s after softplc stop\n{plc.story(t0)}"
        time.sleep(0.3)  # the PLC scans on, stopped: the lamp stays off, the clients attached
        assert not plc.device.lamp()
        assert not clients.lost, f"a service let its client go: {clients.lost}"
        assert plc.proc.poll() is None
    finally:
        clients.close()
