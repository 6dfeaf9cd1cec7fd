"""`softplc run` compiles its start program once, in a compile process, and every scan process
loads that compiled form: the first and a supervisor's restart of a killed one (docs/design.md
section 12; issue 40 item 2). Counted by SOFTPLC_COMPILE_LOG, a line per compile."""

from __future__ import annotations

import os
import signal
from pathlib import Path

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
    assert first["start_program"]["compiled_by"] == "compile process"
    assert first["analysis"] is not None  # analysed where it was compiled, shown all the same
    os.kill(first["scan_pid"], signal.SIGKILL)
    again = eventually_reachable(
        lambda: (s := run.status()).get("restarts") == 1 and s["state"] == "RUNNING" and s,
        60, "the restarted scan process RUNNING")
    assert again["scan_pid"] != first["scan_pid"]
    assert again["start_program"]["compiled_by"] == "compile process"
    assert again["program_hash"] == first["program_hash"]
    lines = log.read_text(encoding="utf-8").splitlines()
    # One compile, by the CLI's compile process; none in the CLI or in either scan process.
    assert len(lines) == 1, lines
    pid, name, source = lines[0].split(" ", 2)
    assert name == "softplc-compile" and source == "programs/transport.yaml"
    assert int(pid) not in (run.proc.pid, first["scan_pid"], again["scan_pid"])
    assert run.stop() == 0
