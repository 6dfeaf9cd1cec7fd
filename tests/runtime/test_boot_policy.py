"""The boot policy (issue 30 item 4; docs/retain.md, boot policy): what a start of the machine
or of `softplc run` does with a PLC that ran before: stay stopped (the default), warm start,
cold start. Kept in the state directory, shown in status, `softplc status` and the page.

Real `softplc run` processes (loopback only, bounded): with the policy stop, a kill -9 of the
whole process group and a new `softplc run --start` without the flag come up STOPPED with the
program loaded and its marking kept; with warm the same comes up RUNNING. In process: cold.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.runtime.test_retain_per_variable import write
from tests.support import eventually_reachable, free_port

ROOT = Path(__file__).resolve().parents[2]
MS = 1_000_000


class Run:
    """One `softplc run programs/transport.yaml --start` in its own session."""

    def __init__(self, state: Path, *extra: str) -> None:
        self.api_port = free_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
             "--plant", "transport", "--quiet", "--opcua", "off", "--modbus", "off",
             "--api", f"127.0.0.1:{self.api_port}", "--state-dir", str(state),
             "--retain-interval", "100ms", "--watchdog", "100", "--on-stall", "continue",
             *extra],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        self.lines: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        self.api = ApiClient(f"http://127.0.0.1:{self.api_port}", timeout_s=5, state_dir=state)

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    def status(self) -> dict[str, Any]:
        return self.api.status()

    def kill_group(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(10)


@pytest.fixture
def runs() -> Iterator[list[Run]]:
    started: list[Run] = []
    yield started
    for run in started:
        run.kill_group()


def run_and_kill(state: Path, runs: list[Run], *extra: str) -> dict[str, Any]:
    """Run until a snapshot of a RUNNING transport with parts under way, then kill -9 the
    whole group (a power loss as far as the state directory can tell)."""
    first = Run(state, *extra)
    runs.append(first)
    seen: dict[str, Any] = eventually_reachable(
        lambda: (s := first.status())["state"] == "RUNNING" and s["retain"]["writes"] >= 2
        and s, 60, "a RUNNING transport with snapshots", show=lambda: first.lines[-5:])
    first.kill_group()
    return seen


def test_stop_policy_comes_up_stopped_with_the_program_after_a_kill_of_the_group(
        tmp_path: Path, runs: list[Run]) -> None:
    state = tmp_path / "state"
    before = run_and_kill(state, runs, "--boot-policy", "stop")
    assert before["boot_policy"] == "stop"
    assert (state / "boot_policy").read_text().strip() == "stop"
    again = Run(state)  # the same command line, without the flag: the kept policy
    runs.append(again)
    status = eventually_reachable(lambda: (s := again.status())["scan_count"] > 5 and s, 60,
                                  "the restarted PLC", show=lambda: again.lines[-5:])
    assert status["state"] == "STOPPED" and status["program"] == "transport"
    assert status["start_mode"] == "warm", status["start_reason"]
    assert "boot policy stop: not started" in status["start_reason"]
    assert status["boot_policy"] == "stop" and "kept in" in status["boot_policy_source"]
    assert status["marking"], "the marking of the killed run is kept (resume continues it)"
    cli = subprocess.run(
        [sys.executable, "-m", "softplc.cli", "status", "--api",
         f"http://127.0.0.1:{again.api_port}", "--state-dir", str(state)],
        cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert cli.returncode == 0, cli.stderr
    assert "boot policy stop (kept in" in cli.stdout
    assert again.api.command("resume")["ok"]
    eventually_reachable(lambda: again.status()["state"] == "RUNNING", 30, "resumed")


def test_warm_policy_resumes_running_after_a_kill_of_the_group(
        tmp_path: Path, runs: list[Run]) -> None:
    state = tmp_path / "state"
    run_and_kill(state, runs, "--boot-policy", "warm")
    again = Run(state)
    runs.append(again)
    status = eventually_reachable(lambda: (s := again.status())["scan_count"] > 5 and s, 60,
                                  "the restarted PLC", show=lambda: again.lines[-5:])
    assert status["state"] == "RUNNING" and status["boot_policy"] == "warm"
    assert status["start_mode"] == "warm" and status["start_reason"].endswith("-> RUNNING")


def test_without_a_kept_policy_the_default_is_stop(tmp_path: Path, runs: list[Run]) -> None:
    """A first start with --start starts (the state directory never held a snapshot); the
    restart after a kill of the group does not."""
    state = tmp_path / "state"
    before = run_and_kill(state, runs)
    assert before["boot_policy"] == "stop" and before["boot_policy_source"] == "default"
    assert not (state / "boot_policy").exists()
    (state / "boot_policy").write_text("sometimes\n")  # damaged: the safe default, said
    again = Run(state)
    runs.append(again)
    status = eventually_reachable(lambda: (s := again.status())["scan_count"] > 5 and s, 60,
                                  "the restarted PLC", show=lambda: again.lines[-5:])
    assert status["state"] == "STOPPED" and status["boot_policy"] == "stop"
    assert "'sometimes'" in status["boot_policy_source"]


def cold_loop(program: str, state: Path, scans: int, policy: str) -> ScanLoop:
    config = LoopConfig(program=program, start=True, period_ns=10 * MS, max_scans=scans,
                        state_dir=str(state), boot_policy=policy)
    return ScanLoop(config, None, None, VirtualClock(10**12))


def test_cold_policy_starts_from_the_initial_marking_keeping_persistent(tmp_path: Path) -> None:
    program, state = write(tmp_path), tmp_path / "state"
    first = cold_loop(program, state, 10, "warm")
    first.runner.plc.image.mw[:3] = (11, 22, 33)
    first.run()
    cold = cold_loop(program, state, 12, "cold")
    assert cold.start_mode == "cold" and "boot policy cold" in cold.start_reason
    cold.run()
    plc = cold.runner.plc
    assert plc.state is PlcState.RUNNING  # it was RUNNING: --start starts it again
    assert plc.marking() == {"counted": 3, "scratch": 4, "total": 6}  # total persisted (3)
    assert (int(plc.image.mw[1]), int(plc.image.mw[2])) == (0, 33)
    # An operator's stop is not undone by a restart, whatever the policy.
    stopping = cold_loop(program, state, 14, "warm")
    stopping.pending.append(ProgramCommand(Command.STOP))
    stopping.run()
    assert stopping.runner.plc.state is PlcState.STOPPED
    stopped = cold_loop(program, state, 16, "cold")
    stopped.run()
    assert stopped.runner.plc.state is PlcState.STOPPED
    assert stopped.runner.plc.marking() == {"src": 3, "scratch": 1, "total": 6}


def test_the_supervisors_restart_of_a_crashed_scan_process_stays_warm(tmp_path: Path) -> None:
    program, state = write(tmp_path), tmp_path / "state"
    cold_loop(program, state, 10, "warm").run()
    config = LoopConfig(program=program, start=True, period_ns=10 * MS, max_scans=12,
                        state_dir=str(state), boot_policy="stop", restarts=1)
    again = ScanLoop(config, None, None, VirtualClock(10**12))
    assert again.start_mode == "warm" and again.runner.plc.state is PlcState.RUNNING
    again.retain.close()  # type: ignore[union-attr]
