"""`softplc run` compiles its start program once (a small one in the CLI, a big one in a compile
process of the CLI's), and every scan process loads that compiled form: the first and a
supervisor's restart of a killed one (docs/design.md section 12; issue 40 item 2). Counted by
SOFTPLC_COMPILE_LOG, a line per compile."""

from __future__ import annotations

import os
import shutil
import signal
from pathlib import Path

import pytest

from softplc.bench import netgen
from softplc.runtime.supervise.startprog import IN_CLI_BYTES, StartRequest, compile_start
from tests.runtime.test_supervision import ROOT, Run, runs  # noqa: F401 (the fixture)
from tests.support import eventually_reachable


def test_the_start_program_is_compiled_once_for_a_start_and_a_restart(
        tmp_path: Path, runs: list[Run]) -> None:  # noqa: F811 (the fixture)
    log = tmp_path / "compiles.log"
    run = Run(ROOT, "programs/transport.yaml", tmp_path / "state", "--plant", "transport",
              env={"SOFTPLC_COMPILE_LOG": str(log)})
    runs.append(run)
    first = eventually_reachable(lambda: (s := run.status())["state"] == "RUNNING" and s, 60,
                                 "RUNNING")
    assert first["start_program"]["compiled_by"].startswith("softplc run")
    assert first["analysis"] is not None  # analysed where it was compiled, shown all the same
    os.kill(first["scan_pid"], signal.SIGKILL)
    again = eventually_reachable(
        lambda: (s := run.status()).get("restarts") == 1 and s["state"] == "RUNNING" and s,
        60, "the restarted scan process RUNNING")
    assert again["scan_pid"] != first["scan_pid"]
    assert again["start_program"]["compiled_by"] == first["start_program"]["compiled_by"]
    assert again["program_hash"] == first["program_hash"]
    lines = log.read_text(encoding="utf-8").splitlines()
    # One compile, by the CLI (transport is small: compile_start); none in a scan process.
    assert len(lines) == 1, lines
    pid, _, source = lines[0].split(" ", 2)
    assert int(pid) == run.proc.pid and source == "programs/transport.yaml", lines
    assert first["start_program"]["compiled_by"] == f"softplc run (pid {pid})"
    assert run.stop() == 0


def test_a_big_start_program_is_compiled_in_a_compile_process(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "programs").mkdir()
    shutil.copytree(ROOT / "io_images", tmp_path / "io_images")
    program = tmp_path / "programs" / "ring.yaml"
    program.write_text(netgen.to_yaml(netgen.ring(1200), "../io_images/transport.yaml"),
                       encoding="utf-8")
    assert program.stat().st_size > IN_CLI_BYTES
    log = tmp_path / "compiles.log"
    monkeypatch.setenv("SOFTPLC_COMPILE_LOG", str(log))
    start = compile_start(StartRequest(str(program)))
    pid, name, _ = log.read_text(encoding="utf-8").split(" ", 2)
    assert name == "softplc-compile" and int(pid) == start.compiled_by != os.getpid()
    net = start.load()  # what a scan process does with it: no YAML parsed here
    assert len(log.read_text(encoding="utf-8").splitlines()) == 1
    assert net.program_hash == start.program_hash and len(net.transitions) == 1200
    assert start.boot is not None and start.boot.program_hash == start.program_hash
