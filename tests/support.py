"""What many test files need: a free loopback port, bounded polling, a real `softplc run`
process, a simulated Modbus server.

Owns: `free_port`; `wait_until` (a truth value the caller asserts) and `eventually` (the first
truthy value, or AssertionError), both bounded by `timeout_s`; `eventually_reachable`, the
same for processes that refuse connections while they start; `softplc_run`, a real `softplc
run` process, ready once a probe says so and ended (SIGTERM, then SIGKILL) whatever the test
did; `SimModbusServer`, a real
pymodbus 3.16.1 server on 127.0.0.1 in its own thread and loop that records every request.
Does not know: any test's subject. Modules with more behaviour (a remote-I/O module with a
communication watchdog: tests/devices/remote_io_device.py) build on these.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

from pymodbus.pdu import ModbusPDU
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from softplc.api.client import ApiError

T = TypeVar("T")
ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (for servers that cannot take 0)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])



def npm_modules(package_dir: Path, cache: Path, what: str) -> Path:
    """The node modules package_dir/package.json names, installed once from the npm registry into
    cache (again when package.json changes); the caller's test skips, saying why, where node or
    npm is missing (.ci/run installs them). The independent clients of tests/opcua (node-opcua)
    and tests/sparkplug (Eclipse Tahu JS) come this way."""
    import pytest

    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node/npm not installed (apt-get install nodejs npm; .ci/run does)")
    package = (package_dir / "package.json").read_bytes()
    stamp = cache / "installed.sha256"
    digest = hashlib.sha256(package).hexdigest()
    if not stamp.exists() or stamp.read_text() != digest:
        cache.mkdir(parents=True, exist_ok=True)
        (cache / "package.json").write_bytes(package)
        done = subprocess.run([npm, "install", "--no-audit", "--no-fund", "--prefix", str(cache)],
                              capture_output=True, text=True, timeout=300, check=False)
        if done.returncode != 0:
            pytest.fail(f"npm install of {what} failed:\n{done.stderr[-2000:]}")
        stamp.write_text(digest)
    return cache / "node_modules"

def wait_until(predicate: Callable[[], object], timeout_s: float = 10.0,
               step_s: float = 0.01) -> bool:
    """Whether `predicate` became true within `timeout_s` (asked once more at the deadline)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return bool(predicate())


def eventually(probe: Callable[[], T | None], timeout_s: float = 5.0, what: str = "condition",
               *, step_s: float = 0.01, show: Callable[[], object] | None = None,
               errors: tuple[type[BaseException], ...] = ()) -> T:
    """The first truthy result of `probe`, polled every `step_s` until `timeout_s`; else an
    AssertionError naming `what` (and what `show` gives then). `errors` raised by the probe
    count as not yet."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            result = probe()
        except errors:
            result = None
        if result:
            return result
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s} s: {what}{_seen(show, errors)}")
        time.sleep(step_s)


def eventually_reachable(probe: Callable[[], T | None], timeout_s: float = 30.0,
                         what: str = "", show: Callable[[], object] | None = None) -> T:
    """`eventually` for a PLC process that is starting or restarting: its Modbus and HTTP
    sides refuse connections meanwhile (OSError, ApiError count as not yet)."""
    return eventually(probe, timeout_s, what, step_s=0.05, show=show, errors=(OSError, ApiError))


def _seen(show: Callable[[], object] | None, errors: tuple[type[BaseException], ...]) -> str:
    if show is None:
        return ""
    try:
        return f" (last seen: {show()})"
    except errors as exc:
        return f" (last seen: {exc})"


@contextlib.contextmanager
def softplc_run(args: Sequence[str], ready: Callable[[], object], *, cwd: Path = ROOT,
                timeout_s: float = 60.0, stdout: int = subprocess.PIPE,
                what: str = "softplc run answering",
                errors: tuple[type[BaseException], ...] = (OSError, ApiError, ValueError)
                ) -> Iterator[subprocess.Popen[str]]:
    """`softplc run ARGS` as a real process (the checkout's softplc, from `cwd`), yielded once
    `ready()` is truthy (`errors` it raises count as not yet: a server still starting refuses
    or half-answers; bounded by `timeout_s`: the processes spawn on a loaded machine), ended
    at the end with SIGTERM, then SIGKILL."""
    proc = subprocess.Popen([sys.executable, "-m", "softplc.cli", "run", *args], cwd=cwd,
                            stdout=stdout, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        def up() -> object:
            if proc.poll() is not None:
                raise AssertionError(f"softplc run ended: {proc.communicate()}")
            return ready()

        eventually(up, timeout_s, what, step_s=0.1, errors=errors)
        yield proc
    finally:
        stop_process(proc)


def stop_process(proc: subprocess.Popen[Any], grace_s: float = 15.0) -> None:
    """SIGTERM, then SIGKILL after `grace_s`: a test never leaves a process behind."""
    proc.terminate()
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(10)


class SimModbusServer:
    """A simulated Modbus TCP server: 64 coils, discrete inputs, holding and input registers,
    all 0, in a background loop; restartable on the same port. Records every request as
    (function code, address, count). Start with start(), end with dispose()."""

    def __init__(self, port: int | None = None, call_timeout_s: float = 2.0) -> None:
        self.port = port or free_port()
        self.call_timeout_s = call_timeout_s
        self.requests: list[tuple[int, int, int]] = []
        self._lock = threading.Lock()
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        self.server: ModbusTcpServer | None = None

    def _call(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(self.call_timeout_s)

    def _trace(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU:
        if not sending:
            with self._lock:
                self.requests.append((pdu.function_code, pdu.address, pdu.count))
        return pdu

    async def _start(self) -> None:
        device = SimDevice(
            id=0,
            simdata=(
                [SimData(0, values=[False] * 64, datatype=DataType.BITS)],
                [SimData(0, values=[False] * 64, datatype=DataType.BITS)],
                [SimData(0, values=[0] * 64, datatype=DataType.REGISTERS)],
                [SimData(0, values=[0] * 64, datatype=DataType.REGISTERS)],
            ),
        )
        self.server = ModbusTcpServer(
            device, address=("127.0.0.1", self.port), trace_pdu=self._trace
        )
        await self.server.serve_forever(background=True)

    def start(self) -> None:
        self._call(self._start())

    def stop(self) -> None:
        if self.server is not None:
            self._call(self.server.shutdown())
            self.server = None

    def set(self, fc: int, address: int, values: list[Any]) -> None:
        assert self.server is not None
        self._call(self.server.async_setValues(0, fc, address, values))

    def get(self, fc: int, address: int, count: int) -> list[Any]:
        assert self.server is not None
        return list(self._call(self.server.async_getValues(0, fc, address, count)))

    def take_requests(self) -> list[tuple[int, int, int]]:
        with self._lock:
            taken, self.requests = self.requests, []
        return taken

    def dispose(self) -> None:
        self.stop()
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(timeout=2)
        self.loop.close()
