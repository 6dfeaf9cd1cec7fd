"""A real `softplc run` for the whole-system test: start, signal, kill its processes, clean up.

Owns: the command line (free loopback ports for Modbus, HTTP and OPC UA, a state directory,
the programs directory, TMPDIR of its own), the processes it saw (supervisor, scan,
communication, compile), how a run ended (exit code, time to exit, time until the module's
coils read safe) and what a run may leave behind (processes, /dev/shm entries, temp files).
Does not know: the model or what the PLC should be doing.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from tests.support import free_port
from tests.system.programs import COILS, Library, Module

ROOT = Path(__file__).resolve().parents[2]
UP_WITHIN_S = 60.0  # two processes spawning on a loaded 2-core machine: seconds, sometimes 20
EXIT_WITHIN_S = 2.0  # docs/operations.md: SIGTERM/SIGINT stop everything within 2 s
EXIT_SLACK_S = 3.0  # what a loaded test machine adds before the test calls it a hang
SAFE_WITHIN_S = 1.0  # docs/faults.md: every stop path leaves the outputs safe within 1 s


@dataclass
class Ending:
    """How one run ended."""

    how: str
    code: int | None
    exit_s: float
    safe_s: float | None  # None: the module was down, nothing to read
    log_tail: str


@dataclass
class Run:
    """One `softplc run` process tree."""

    proc: subprocess.Popen[bytes]
    state_dir: Path
    modbus: int
    api_port: int
    opcua: int | None
    log: Path
    pids: set[int] = field(default_factory=set)

    @property
    def api(self) -> ApiClient:
        return ApiClient(f"http://127.0.0.1:{self.api_port}", timeout_s=8,
                         state_dir=self.state_dir)

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    @property
    def opcua_url(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.opcua}"

    @property
    def token(self) -> str:
        return (self.state_dir / "api_token").read_text(encoding="utf-8").strip()

    def children(self) -> list[int]:
        return [pid for pid in _children(self.proc.pid) if "resource_tracker" not in _cmd(pid)]

    def listener(self, port: int) -> int | None:
        """The child process listening on `port` (the communication process serves Modbus
        and HTTP, the OPC UA process its port)."""
        inodes = _listening_inodes(port)
        for pid in self.children():
            try:
                fds = list(Path(f"/proc/{pid}/fd").iterdir())
            except OSError:
                continue
            for fd in fds:
                try:
                    target = os.readlink(fd)
                except OSError:
                    continue
                if target.startswith("socket:[") and target[8:-1] in inodes:
                    return pid
        return None

    def remember(self, status: dict[str, Any]) -> None:
        """Every process the run showed, so that the end can check that none is left."""
        self.pids.add(self.proc.pid)
        self.pids.update(_children(self.proc.pid))
        for pid in (status.get("scan_pid"), (status.get("compile_process") or {}).get("pid")):
            if isinstance(pid, int) and pid > 0:
                self.pids.add(pid)

    def tail(self) -> str:
        try:
            return self.log.read_text(encoding="utf-8", errors="replace")[-1500:]
        except OSError:
            return ""


class Rig:
    """Starts runs against one module and one programs directory; `close` ends everything."""

    def __init__(self, base: Path, library: Library, module: Module, *,
                 opcua: bool = True) -> None:
        self.base, self.library, self.module, self.opcua = base, library, module, opcua
        self.tmp = base / "tmp"  # the runs' TMPDIR: whatever they leave there is counted
        self.tmp.mkdir(parents=True, exist_ok=True)
        self.run: Run | None = None
        self.ended: list[Run] = []
        self.dirs = 0

    def new_state_dir(self) -> Path:
        self.dirs += 1
        return self.base / f"state{self.dirs}"

    def start(self, state_dir: Path, program: str | None, start: bool,
              cwd: Path | None = None) -> Run:
        assert self.run is None, "one run at a time"
        modbus, api, ua = free_port(), free_port(), free_port() if self.opcua else None
        log = self.base / f"run{len(self.ended) + 1}.log"
        args = [sys.executable, "-m", "softplc.cli", "run", "--quiet", "--period", "10ms",
                "--modbus", f"127.0.0.1:{modbus}", "--api", f"127.0.0.1:{api}",
                "--opcua", f"127.0.0.1:{ua}" if ua else "off", "--state-dir", str(state_dir),
                "--programs-dir", str(self.library.root), "--watchdog", "100",
                "--on-stall", "continue", "--boot-policy", "warm"]  # the model's restarts
        if program is not None:
            args.append(str(self.library.path(program)))
        if start:
            args.append("--start")
        env = {**os.environ, "TMPDIR": str(self.tmp)}
        with log.open("wb") as out:  # a pipe nobody reads would block the run
            # A run without a program confines plain-text downloads to its cwd, even those of
            # --programs-dir (test_lifecycle_regressions.py): the programs live under base.
            proc = subprocess.Popen(args, cwd=cwd or self.base, stdout=out,
                                    stderr=subprocess.STDOUT,
                                    env=env)
        self.run = Run(proc, state_dir, modbus, api, ua, log)
        self.run.pids.add(proc.pid)
        return self.run

    def stop(self, how: str) -> Ending:
        """End the run by SIGTERM, SIGINT or SIGKILL of the supervisor; measure the exit and
        the module's coils going safe (polled every 5 ms from the signal)."""
        run = self.run
        assert run is not None
        sig = {"SIGTERM": signal.SIGTERM, "SIGINT": signal.SIGINT,
               "SIGKILL": signal.SIGKILL}[how]
        with_module = self.module.server is not None
        t0 = time.monotonic()
        run.proc.send_signal(sig)
        safe_s = self._until_safe(t0) if with_module else None
        with contextlib.suppress(subprocess.TimeoutExpired):
            run.proc.wait(EXIT_WITHIN_S + EXIT_SLACK_S)
        exit_s = time.monotonic() - t0
        if run.proc.poll() is None:
            run.proc.kill()
            run.proc.wait(10)
            code = None
        else:
            code = run.proc.returncode
        if sig is signal.SIGKILL:  # the children stop on their own (PR_SET_PDEATHSIG)
            _wait_gone(run.pids - {run.proc.pid}, EXIT_WITHIN_S + EXIT_SLACK_S)
        self.ended.append(run)
        self.run = None
        return Ending(how, code, exit_s, safe_s, run.tail())

    def _until_safe(self, t0: float, limit_s: float = 5.0) -> float:
        while any(self.module.get(1, 0, len(COILS))):
            if time.monotonic() - t0 > limit_s:
                return float("inf")
            time.sleep(0.005)
        return time.monotonic() - t0

    def close(self) -> None:
        """Whatever happened: no process of ours stays."""
        if self.run is not None:
            with contextlib.suppress(Exception):  # already failing: killed below
                self.stop("SIGTERM")
        for run in [*self.ended, *([self.run] if self.run else [])]:
            for pid in run.pids:
                if _alive(pid):
                    os.kill(pid, signal.SIGKILL)

    # -- what a run may leave behind --------------------------------------------------------

    def leftovers(self) -> list[str]:
        """Processes, /dev/shm entries of our supervisors, temp files: none may remain."""
        found: list[str] = []
        runs = [*self.ended, *([self.run] if self.run else [])]
        # multiprocessing's resource tracker ends when it reads EOF after its supervisor
        _wait_gone({pid for run in runs for pid in run.pids}, EXIT_WITHIN_S)
        for run in runs:
            found += [f"process {pid} ({_cmd(pid)[:80]})" for pid in sorted(run.pids)
                      if _alive(pid)]
        sups = {str(run.proc.pid) for run in runs}
        shm = Path("/dev/shm")
        found += [f"/dev/shm/{entry.name}" for entry in shm.glob("softplc_*")
                  if entry.name.split("_")[1] in sups]
        found += [f"temp {path}" for path in self.tmp.rglob("*")]
        for run in runs:
            found += [f"temp {path}" for path in run.state_dir.glob(".*tmp")]
        return found


def wait_api(run: Run, timeout_s: float = UP_WITHIN_S) -> dict[str, Any]:
    """The first status the run's API gives that is not stale (the scan publishes)."""
    deadline = time.monotonic() + timeout_s
    last: object = None
    while time.monotonic() < deadline:
        if run.proc.poll() is not None:
            raise AssertionError(f"softplc run exited ({run.proc.returncode}): {run.tail()}")
        try:
            status = run.api.status()
        except (ApiError, ApiUnreachable, OSError) as exc:
            last = exc
        else:
            if not status.get("stale") and _listens(run.opcua):
                run.remember(status)
                return status
            last = "stale" if status.get("stale") else "OPC UA not listening"
        time.sleep(0.1)
    raise AssertionError(f"the API did not answer within {timeout_s} s ({last}): {run.tail()}")


def _listens(port: int | None) -> bool:
    if port is None:
        return True
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _listening_inodes(port: int) -> set[str]:
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
                found.add(fields[9])
    return found


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def _cmd(pid: int) -> str:
    try:
        return (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
                .decode(errors="replace"))
    except OSError:
        return ""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait_gone(pids: set[int], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while any(_alive(p) for p in pids) and time.monotonic() < deadline:
        time.sleep(0.02)
