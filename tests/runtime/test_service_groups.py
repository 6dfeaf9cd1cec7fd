"""The service processes of `softplc run` (runtime/serve/comm.py `service_groups`, docs/design.md
section 7): Modbus, HTTP and OPC UA each in a process of its own, at the niceness the design
gives it, so that one that stops serving altogether (SIGSTOP: the worst a client can make it
do) leaves the others answering. Causal, not timed: while the HTTP process is stopped, Modbus
answers with scans that happened after the stop; while the Modbus process is stopped, HTTP
does. A real `softplc run` on free loopback ports, killed at the end whatever happened.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from softplc.hmi.map import STATUS_SCAN_COUNT
from softplc.runtime.serve.comm import CommConfig, service_groups
from softplc.runtime.shared.procs import children
from tests.support import eventually, free_port

ROOT = Path(__file__).resolve().parents[2]
# Three processes start, asyncua's in seconds, on a loaded 2-core machine.
wait_for = functools.partial(eventually, timeout_s=60.0, step_s=0.1)


def test_each_service_has_a_process_of_its_own_at_its_niceness() -> None:
    config = CommConfig(modbus=("127.0.0.1", 1), api=("127.0.0.1", 2), opcua=("127.0.0.1", 3))
    groups = service_groups(config)
    assert list(groups) == ["modbus", "http", "opcua"]
    served = {name: [s for s in ("modbus", "api", "opcua") if getattr(group, s) is not None]
              for name, group in groups.items()}
    assert served == {"modbus": ["modbus"], "http": ["api"], "opcua": ["opcua"]}
    assert groups["modbus"].nice < groups["http"].nice < groups["opcua"].nice


def test_a_service_that_is_off_has_no_process() -> None:
    assert list(service_groups(CommConfig(api=None, opcua=None))) == ["modbus"]
    assert list(service_groups(CommConfig(modbus=None, opcua=("127.0.0.1", 3)))) == [
        "http", "opcua"]
    assert service_groups(CommConfig(modbus=None, api=None)) == {}


@dataclass(frozen=True)
class Plc:
    proc: subprocess.Popen[str]
    modbus: int
    api: int
    opcua: int
    state: Path


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[Plc]:
    modbus, api, opcua = free_port(), free_port(), free_port()
    with (tmp_path / "stderr.txt").open("w") as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
             "--modbus", f"127.0.0.1:{modbus}", "--api", f"127.0.0.1:{api}",
             "--opcua", f"127.0.0.1:{opcua}", "--state-dir", str(tmp_path / "state"), "--quiet",
             "--period", "10ms"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=stderr, text=True)
    try:
        yield Plc(proc, modbus, api, opcua, tmp_path / "state")
    finally:
        for pid in children(proc.pid):  # a stopped child would not end with its parent
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGCONT)
        proc.kill()
        proc.wait(10)


def listener(parent: int, port: int) -> int | None:
    """The child of `parent` holding the socket that listens on `port` (/proc, Linux)."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
            inodes.add(f"socket:[{fields[9]}]")
    for pid in children(parent):
        with contextlib.suppress(OSError):
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                with contextlib.suppress(OSError):
                    if os.readlink(fd) in inodes:
                        return pid
    return None


def nice_of(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[16])


def scan_count(port: int) -> int | None:
    """The scan count the Modbus slave serves now, None when it does not answer in 2 s."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
    try:
        if not client.connect():
            return None
        reply = client.read_input_registers(1024 + STATUS_SCAN_COUNT, count=2, device_id=1)
        return None if reply.isError() else (reply.registers[0] << 16) | reply.registers[1]
    except Exception:
        return None
    finally:
        client.close()


def http_scan_count(port: int, timeout_s: float = 2.0) -> int | None:
    """The scan count HTTP /status reports now, None when it does not answer in time."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/v1/status",
                                    timeout=timeout_s) as reply:
            document = json.loads(reply.read())
    except (OSError, ValueError):
        return None
    count = document.get("scan_count")
    return count if isinstance(count, int) and not document.get("stale") else None


def declared_bomb(plc: Plc) -> bytes:
    """The answer to a JSON write that declares 500 KB (a bomb's size) and sends none of it."""
    token = (plc.state / "api_token").read_text(encoding="utf-8").strip()
    with socket.create_connection(("127.0.0.1", plc.api), timeout=10) as sock:
        sock.sendall(b"PUT /api/v1/symbols/hold HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                     b"Content-Type: application/json\r\nContent-Length: 500000\r\n"
                     b"Authorization: Bearer " + token.encode() + b"\r\n\r\n")
        return sock.recv(4096)


def opcua_answers(port: int) -> bool:
    """An OPC UA Hello gets an Acknowledge (the OPC UA process's loop runs)."""
    url = f"opc.tcp://127.0.0.1:{port}".encode()
    body = struct.pack("<5Ii", 0, 65536, 65536, 0, 0, len(url)) + url
    hello = b"HELF" + struct.pack("<I", 8 + len(body)) + body
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=2) as sock:
            sock.sendall(hello)
            return sock.recv(8)[:3] == b"ACK"
    except OSError:
        return False


def test_modbus_http_and_opcua_are_separate_processes_that_do_not_wait_for_each_other(
        plc: Plc) -> None:
    first = wait_for(lambda: scan_count(plc.modbus), what="Modbus answers")
    wait_for(lambda: http_scan_count(plc.api), what="HTTP answers")
    wait_for(lambda: opcua_answers(plc.opcua) or None, what="OPC UA answers")
    pids = {name: wait_for(lambda port=port: listener(plc.proc.pid, port),  # type: ignore[misc]
                           what=f"the process listening on {port}")
            for name, port in (("modbus", plc.modbus), ("http", plc.api),
                               ("opcua", plc.opcua))}
    assert len(set(pids.values())) == 3, pids
    nice = {name: nice_of(pid) for name, pid in pids.items()}
    assert nice["modbus"] < nice["http"] < nice["opcua"], nice
    # Refused before a byte of the body is read: the answer comes while the client sends none.
    answer = declared_bomb(plc)
    assert answer.startswith(b"HTTP/1.1 413"), answer
    assert b"at most" in answer and answer.count(b"\n") < 12, answer  # one line, no traceback

    os.kill(pids["http"], signal.SIGSTOP)
    try:
        # The HTTP process cannot answer now; Modbus and OPC UA still do, and Modbus serves
        # scans that ran after the stop (the count moves on).
        assert http_scan_count(plc.api, timeout_s=1.0) is None
        stopped_at = wait_for(lambda: scan_count(plc.modbus), what="Modbus answers")
        assert stopped_at >= first
        wait_for(lambda: ((n := scan_count(plc.modbus)) is not None and n > stopped_at) or None,
                 what="Modbus serves newer scans while HTTP is stopped")
        assert opcua_answers(plc.opcua)
    finally:
        os.kill(pids["http"], signal.SIGCONT)
    wait_for(lambda: http_scan_count(plc.api), what="HTTP answers again")

    os.kill(pids["modbus"], signal.SIGSTOP)
    try:
        assert scan_count(plc.modbus) is None
        seen = wait_for(lambda: http_scan_count(plc.api), what="HTTP answers")
        wait_for(lambda: ((n := http_scan_count(plc.api)) is not None and n > seen) or None,
                 what="HTTP serves newer scans while Modbus is stopped")
    finally:
        os.kill(pids["modbus"], signal.SIGCONT)
    wait_for(lambda: scan_count(plc.modbus), what="Modbus answers again")
    assert plc.proc.poll() is None, (plc.state.parent / "stderr.txt").read_text()
