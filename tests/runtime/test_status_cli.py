"""`softplc status` and the console (issue 26.1-3): the status shows a fault's reason and the
timed firings in progress with their time left; a closed stdout (`softplc status | head -1`)
ends no command with a traceback; `softplc --help` shows its whole description.

The status is read off a real ScanLoop (virtual clock), and end to end from a real `softplc
run` over its HTTP API, whose remote I/O device is a port where nothing answers."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api.clicmds import format_status
from softplc.cli import DESCRIPTION
from softplc.core.judge import Observed
from softplc.core.lifecycle import PlcState
from softplc.runtime import statusdoc
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from tests.core.helpers import write_io
from tests.runtime.test_supervision import ROOT, Run
from tests.support import eventually_reachable, free_port

MS = 1_000_000
TIMED = """program: timed
io_image: io.yaml
places:
  d: {tokens: 1}
  e: {}
transitions:
  work: {from: [d], to: [e], duration: 2s, outputs: [m]}
"""

DEAD_IO = """drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: 0.05, startup_s: 0}}
symbols:
  lamp: {{address: "%QX0.0", channel: "coil:0", safe: false}}
"""
DEAD = """program: lamp
io_image: io.yaml
places:
  d: {tokens: 1}
  e: {}
transitions:
  work: {from: [d], to: [e], duration: 10min, outputs: [lamp]}
"""


def test_status_shows_a_timed_firing_in_progress_and_the_fault_reason(tmp_path: Path) -> None:
    write_io(tmp_path)
    (tmp_path / "timed.yaml").write_text(TIMED, encoding="utf-8")
    clock = VirtualClock(0)
    loop = ScanLoop(LoopConfig(program=str(tmp_path / "timed.yaml"), start=True,
                               period_ns=10 * MS), None, None, clock)
    try:
        for now_ns in range(0, 500 * MS, 10 * MS):  # the firing began at the first scan
            loop.scan_once(now_ns)
        clock.wait_until(500 * MS)
        shown = format_status(statusdoc.document(loop))
        assert "firing      work: 1.5 s left of 2 s" in shown
        assert "fault " not in shown
        loop.runner.judge_now(Observed(overrun="scan 49 took 120.0 ms (budget 100 ms)"),
                              500 * MS)
        assert loop.runner.plc.state is PlcState.FAULTED
        shown = format_status(statusdoc.document(loop))
    finally:
        loop.shutdown()
    assert "state       FAULTED (fault code 1, watchdog)" in shown
    assert "fault       scan 49 took 120.0 ms (budget 100 ms)" in shown


def cli(*args: str, stdout: int | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *args], cwd=ROOT, text=True,
                          stdout=stdout if stdout is not None else subprocess.PIPE,
                          stderr=subprocess.PIPE, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def closed_pipe(*args: str) -> subprocess.CompletedProcess[str]:
    """`softplc ARGS | head -0`, without the race: the reader is gone before the first write."""
    read, write = os.pipe()
    os.close(read)
    try:
        return cli(*args, stdout=write)
    finally:
        os.close(write)


@pytest.fixture(scope="module")
def faulted(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Run]:
    directory = tmp_path_factory.mktemp("dead")
    (directory / "io.yaml").write_text(DEAD_IO.format(port=free_port()), encoding="utf-8")
    (directory / "lamp.yaml").write_text(DEAD, encoding="utf-8")
    run = Run(directory, "lamp.yaml", directory / "state")
    try:
        eventually_reachable(lambda: run.status()["state"] == "FAULTED", 30, "the device fault")
        yield run
    finally:
        run.stop()
        run.kill_group()


def test_softplc_status_says_why_the_plc_faulted(faulted: Run) -> None:
    done = cli("status", "--api", f"http://127.0.0.1:{faulted.api_port}")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "state       FAULTED (fault code 2, device)"
    assert lines[1].startswith("fault       device rio not answering for ")


@pytest.mark.parametrize("args", [("status",), ("status", "--json"), ("--help",),
                                  ("check", "programs/transport.yaml")])
def test_a_closed_stdout_ends_a_command_quietly(faulted: Run, args: tuple[str, ...]) -> None:
    api = ("--api", f"http://127.0.0.1:{faulted.api_port}") if args[0] == "status" else ()
    done = closed_pipe(*args, *api)
    assert done.returncode in (0, 141), done.stderr
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr
    assert done.stderr == ""


def test_help_shows_the_whole_description() -> None:
    done = cli("--help")
    assert done.returncode == 0
    shown = " ".join(done.stdout.split("\n\n", 1)[1].split("positional arguments")[0].split())
    assert shown == DESCRIPTION
