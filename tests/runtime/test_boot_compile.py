"""The boot program is compiled off the scan process (docs/design.md sections 7 and 12; issue 40
item 2): after an accepted download, a supervisor's restart of a killed scan process, and a
`softplc run` without a program, get the state directory's boot program compiled by `softplc
run` (a small one in itself, a big one in a compile process of its own); the scan process
loads the compiled form. A boot program that no longer compiles is reported and the PLC serves.
Real `softplc run` processes, counted by SOFTPLC_COMPILE_LOG (a line per compile: pid, process
name, file); the scan process found by its name in `ps`."""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import pickle
import shutil
import signal
import subprocess
import threading
from pathlib import Path

import pytest

from softplc.bench import netgen
from softplc.program import boot
from softplc.program import bundle as bundles
from softplc.runtime.bootkeeper import Awaited
from softplc.runtime.config import LoopConfig
from softplc.runtime.supervise import startprog
from softplc.runtime.supervise.startprog import (
    COMPILE_PROCESS,
    HERE,
    IN_CLI_BYTES,
    BootForms,
    compile_boot,
)
from tests.runtime.test_supervision import ROOT, Run, runs  # noqa: F401 (the fixture)
from tests.support import eventually_reachable


def compiles(log: Path) -> list[tuple[int, str, str]]:
    """(pid, process name, file) of every compile so far."""
    if not log.exists():
        return []
    return [(int(pid), name, source) for pid, name, source in
            (line.split(" ", 2) for line in log.read_text(encoding="utf-8").splitlines())]


def scan_process(supervisor: int) -> int:
    """The pid of the supervisor's child named softplc-scan in `ps`."""
    listed = subprocess.run(["ps", "-o", "pid=,comm=", "--ppid", str(supervisor)],
                            capture_output=True, text=True, check=False, timeout=10).stdout
    found = [int(pid) for pid, comm in (line.split() for line in listed.splitlines())
             if comm == "softplc-scan"]
    assert len(found) == 1, listed
    return found[0]


def test_a_restart_after_a_download_compiles_the_boot_program_off_the_scan(
        tmp_path: Path, runs: list[Run]) -> None:  # noqa: F811 (the fixture)
    log, state = tmp_path / "compiles.log", tmp_path / "state"
    run = Run(ROOT, "programs/transport.yaml", state, "--plant", "transport",
              env={"SOFTPLC_COMPILE_LOG": str(log)})
    runs.append(run)
    first = eventually_reachable(lambda: (s := run.status())["state"] == "RUNNING" and s, 60,
                                 "RUNNING")
    text = (ROOT / "programs" / "transport.yaml").read_text(encoding="utf-8")
    changed = text.replace("places:\n", "places:\n  spare: {}\n", 1)
    assert changed != text
    assert run.api.download(changed, online=True, name="transport.yaml")["ok"]
    downloaded = eventually_reachable(
        lambda: (s := run.status())["program_hash"] != first["program_hash"] and s, 30,
        "the download running")
    eventually_reachable(lambda: run.status()["scan_count"] > downloaded["scan_count"] + 150,
                         30, "scans after the download (a snapshot of it)")
    scan = scan_process(run.proc.pid)
    assert scan == first["scan_pid"]
    os.kill(scan, signal.SIGKILL)
    again = eventually_reachable(
        lambda: (s := run.status()).get("restarts") == 1 and s["state"] == "RUNNING"
        and not s["stale"] and s, 60, "the restarted scan process RUNNING")
    assert again["program_hash"] == downloaded["program_hash"]
    assert again["start_mode"] == "warm"
    assert "boot program transport.yaml" in again["program_source"]
    by = again["start_program"]["compiled_by"]
    assert by == f"softplc run (pid {run.proc.pid})", by
    seen = compiles(log)
    # The start program by `softplc run`, the download by the scan process's compile process,
    # the boot program for the restart by `softplc run` again: none by a scan process.
    assert [pid == run.proc.pid for pid, _, _ in seen] == [True, False, True], seen
    assert seen[1][1] == "softplc-compile" and seen[-1][1] == "softplc", seen
    assert seen[-1][2].endswith("programs/transport.yaml")
    assert run.stop() == 0

    # `softplc run` without a program: the boot program (the download) compiled by it too.
    log.unlink()
    run = Run(ROOT, "", state, env={"SOFTPLC_COMPILE_LOG": str(log)})
    runs.append(run)
    started = eventually_reachable(lambda: (s := run.status())["program_hash"] and s, 60,
                                   "the boot program loaded")
    assert started["program_hash"] == downloaded["program_hash"]
    assert started["start_program"]["compiled_by"] == f"softplc run (pid {run.proc.pid})"
    assert [(pid, name) for pid, name, _ in compiles(log)] == [(run.proc.pid, "softplc")]
    assert run.stop() == 0


def test_a_boot_program_that_no_longer_compiles_is_reported_and_the_plc_serves(
        tmp_path: Path, runs: list[Run]) -> None:  # noqa: F811 (the fixture)
    log, state = tmp_path / "compiles.log", tmp_path / "state"
    boot.save(state, boot.BootProgram(str(ROOT / "programs" / "gone.yaml"),
                                      "program: gone\nplaces: [\n", str(ROOT), None, "0" * 16))
    run = Run(ROOT, "", state, env={"SOFTPLC_COMPILE_LOG": str(log)})
    runs.append(run)
    status = run.status()
    assert status["state"] == "EMPTY"
    assert status["program_source"].startswith(
        "none (boot program gone.yaml (last accepted) no longer compiles: "), status
    assert [(pid, name) for pid, name, _ in compiles(log)] == [(run.proc.pid, "softplc")]
    os.kill(scan_process(run.proc.pid), signal.SIGKILL)  # a restart reports it likewise
    again = eventually_reachable(
        lambda: (s := run.status()).get("restarts") == 1 and not s["stale"] and s, 60,
        "the restarted scan process")
    assert again["program_source"] == status["program_source"]
    assert all(name != "softplc-scan" for _, name, _ in compiles(log)), compiles(log)
    assert run.stop() == 0


def test_a_big_boot_program_compiles_in_a_compile_process_and_a_bundle_here(
        tmp_path: Path) -> None:
    (tmp_path / "programs").mkdir()
    shutil.copytree(ROOT / "io_images", tmp_path / "io_images")
    text = netgen.to_yaml(netgen.ring(1200), "../io_images/transport.yaml")
    assert len(text) > IN_CLI_BYTES
    config = LoopConfig(root=str(tmp_path), state_dir=str(tmp_path / "state"))
    big = compile_boot(boot.BootProgram(str(tmp_path / "programs" / "ring.yaml"), text,
                                        str(tmp_path)), config)
    assert big.compiled_in == COMPILE_PROCESS and big.compiled_by != os.getpid()
    assert not big.problem and len(big.load().transitions) == 1200
    packed = bundles.pack(bundles.from_files(ROOT / "programs" / "transport.yaml"))
    program = boot.BootProgram("transport.yaml", "", None, packed, "")
    small = compile_boot(program, config)
    assert (small.compiled_in, small.compiled_by) == (HERE, os.getpid())
    assert small.load().name == "transport" and small.serves(program)
    broken = compile_boot(boot.BootProgram("x.yaml", "", None, b"not a zip", ""), config)
    assert broken.problem and not broken.net and broken.serves(broken.boot)


def test_the_compiled_boot_program_is_kept_for_the_next_restart(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    state = tmp_path / "state"
    config = LoopConfig(root=str(ROOT), state_dir=str(state))
    forms = BootForms(multiprocessing.get_context("spawn"))
    assert forms.for_scan(config) == (config, None)  # no boot program: nothing to compile
    text = (ROOT / "programs" / "tank.yaml").read_text(encoding="utf-8")
    boot.save(state, boot.BootProgram(str(ROOT / "programs" / "tank.yaml"), text, str(ROOT)))
    # The compile waits for the test to let it go: on a loaded machine it finished before
    # for_scan returned, and a finished form is handed out as it is (no Awaited).
    go, real_compile = threading.Event(), startprog.compile_boot
    monkeypatch.setattr(startprog, "compile_boot",
                        lambda *args: go.wait(60) and real_compile(*args))
    config, given = forms.for_scan(config)
    assert isinstance(given, Awaited)  # a scan process starts meanwhile, and waits for it
    config, again = forms.for_scan(config)  # a restart before it compiled: the same compile
    go.set()
    compiled = given.receive()
    assert compiled.load().name == "tank" and again.receive() == compiled
    config, kept = forms.for_scan(config)
    assert kept == compiled == config.compiled  # the same boot program: not compiled again
    boot.save(state, boot.BootProgram(str(ROOT / "programs" / "other.yaml"),
                                      text.replace("3s", "4s"), str(ROOT)))
    config, other = forms.for_scan(config)  # another boot program (a download since): compiled
    other = other.receive()
    assert other != compiled and not other.problem and other.serves(boot.load(state))
    pickle.loads(pickle.dumps(dataclasses.replace(config, compiled=given)))  # read: picklable


def test_a_scan_process_gets_no_form_when_softplc_run_stops_first(tmp_path: Path) -> None:
    state = tmp_path / "state"
    text = netgen.to_yaml(netgen.ring(1200), "../../io_images/transport.yaml")
    boot.save(state, boot.BootProgram(str(state / "p" / "ring.yaml"), text, None))
    forms = BootForms(multiprocessing.get_context("spawn"))
    _, given = forms.for_scan(LoopConfig(state_dir=str(state)))
    forms.cancel()
    assert given.receive() is None
