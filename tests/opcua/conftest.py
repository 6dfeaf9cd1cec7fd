"""A real `softplc run` with its OPC UA server on a free loopback port, bounded in time."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from asyncua import Client

from softplc.opcua.client import RefusingAwareClient
from tests.support import free_port

ROOT = Path(__file__).resolve().parents[2]
PATIENCE_S = 30.0


def patient_client(url: str, patience_s: float = PATIENCE_S) -> Client:
    """An asyncua client that waits for the server as an operator's would. OPC UA is served
    last when the CPUs are busy (niceness 10, docs/design.md section 7), and asyncua's client
    drops its connection when the server does not answer its keep-alive probe within one
    second (`watchdog_intervall`): beside 4 busy loops that cut the tests' clients off while
    the server was still working, rebuilding the address space after a download. What the
    tests check is the answers, not how fast a starved server gives them."""
    return RefusingAwareClient(url, timeout=patience_s, watchdog_intervall=patience_s)


def wait_port(port: int, proc: subprocess.Popen[str], timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"softplc run exited ({proc.returncode}); see its run.log")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"nothing listens on 127.0.0.1:{port} after {timeout_s} s")


@dataclass
class Plc:
    proc: subprocess.Popen[str]
    url: str
    port: int
    state_dir: Path

    @property
    def token(self) -> str:
        return (self.state_dir / "api_token").read_text().strip()


def start_plc(program: str, state_dir: Path, *extra: str, plant: str | None = None,
              period: str = "10ms") -> Plc:
    port = free_port()
    args = [sys.executable, "-m", "softplc.cli", "run", program, "--start",
            "--modbus", "off", "--api", "off", "--opcua", f"127.0.0.1:{port}",
            "--state-dir", str(state_dir), "--quiet", "--period", period, *extra]
    if plant:
        args += ["--plant", plant]
    # Output goes to files: a pipe nobody reads fills up and blocks the writer.
    log = (state_dir / "run.log").open("w")
    proc = subprocess.Popen(args, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, text=True)
    log.close()
    try:
        wait_port(port, proc)
    except BaseException:
        stop_plc(proc)
        raise
    return Plc(proc, f"opc.tcp://127.0.0.1:{port}", port, state_dir)


def stop_plc(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)


@pytest.fixture
def transport_plc(tmp_path: Path) -> Iterator[Plc]:
    plc = start_plc("programs/transport.yaml", tmp_path)
    try:
        yield plc
    finally:
        stop_plc(plc.proc)


@pytest.fixture(scope="module")
def shared_plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Plc]:
    """One transport PLC for the tests of a module that leave it as they found it (they
    read, or write and restore; none downloads or changes the lifecycle state for good):
    a start of `softplc run` with OPC UA took 7-15 s of the suite's time in each test."""
    state_dir = tmp_path_factory.mktemp("shared_plc")
    plc = start_plc("programs/transport.yaml", state_dir)
    try:
        yield plc
    finally:
        stop_plc(plc.proc)
