"""SIGTERM to the whole process group (systemd's default KillMode=control-group, GNU
timeout, a terminal's job control): every child hears it with the supervisor. The scan
process then ends on its own, and the supervisor, which had the same signal, must stop, not
take that end for a crash and restart the scan process warm (seen: "scan process exited with
code 0; restarting it warm" while stopping, a restarted scan driving outputs again)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from softplc.api.client import ApiClient, ApiError
from tests.support import eventually, free_port

ROOT = Path(__file__).resolve().parents[2]


def running(api: ApiClient) -> None:
    eventually(lambda: api.status()["state"] == "RUNNING", 60, "softplc run RUNNING",
               step_s=0.1, errors=(OSError, ValueError, ApiError))


def test_a_sigterm_to_the_group_stops_everything_and_restarts_nothing(tmp_path: Path) -> None:
    for attempt in range(2):  # the old supervisor restarted in about half of the stops
        port = free_port()
        proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--plant",
             "transport", "--start", "--api", f"127.0.0.1:{port}", "--modbus", "off",
             "--opcua", "off", "--state-dir", str(tmp_path / f"state{attempt}"), "--quiet"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        try:
            running(ApiClient(f"http://127.0.0.1:{port}", timeout_s=2))
            os.kill(proc.pid, signal.SIGTERM)  # as GNU timeout: the child, then the group
            os.killpg(proc.pid, signal.SIGTERM)
            out, _ = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(10)
        assert proc.returncode == 0, out
        assert "; restarting it warm" not in out and "(restart 1" not in out, out
        assert "outputs safe" in out
