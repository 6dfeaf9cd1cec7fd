"""Every process of a real `softplc run` shows its job in `ps -o comm` and `top` (issue 40,
item 3): the supervisor `softplc`, its children `softplc-scan`, `softplc-modbus`,
`softplc-http` and `softplc-opcua`, the scan process's `softplc-compile`. Before, all of them
were `python` (multiprocessing's Process(name=) names a process for Python only)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from softplc.api.client import ApiClient
from softplc.runtime.shared.procs import COMM_BYTES, children
from softplc.runtime.supervise.supervisor import _TITLES
from tests.support import eventually, free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc, prctl")


def comm(pid: int) -> str:
    return Path(f"/proc/{pid}/comm").read_text().strip()


def is_resource_tracker(pid: int) -> bool:
    """multiprocessing's own helper, started by the library (`python -c ...`): not ours."""
    return b"resource_tracker" in Path(f"/proc/{pid}/cmdline").read_bytes()


def test_each_process_of_softplc_run_shows_its_name(tmp_path: Path) -> None:
    api = free_port()
    client = ApiClient(f"http://127.0.0.1:{api}", timeout_s=5)
    args = [str(ROOT / "programs" / "transport.yaml"), "--start", "--quiet",
            "--modbus", f"127.0.0.1:{free_port()}", "--api", f"127.0.0.1:{api}",
            "--opcua", f"127.0.0.1:{free_port()}", "--state-dir", str(tmp_path / "state"),
            "--watchdog", "100", "--on-stall", "continue"]
    with softplc_run(args, lambda: client.status()["state"] == "RUNNING", cwd=tmp_path,
                     what="softplc run RUNNING with every service") as proc:
        status = client.status()
        compile_pid = status["compile_process"]["pid"]
        assert eventually(lambda: comm(compile_pid) == "softplc-compile", 30,
                          "the compile process named", show=lambda: comm(compile_pid))
        ours = sorted(comm(pid) for pid in children(proc.pid) if not is_resource_tracker(pid))
        assert comm(proc.pid) == "softplc"
        assert comm(status["scan_pid"]) == "softplc-scan"
        assert ours == ["softplc-http", "softplc-modbus", "softplc-opcua", "softplc-scan"]
        assert children(status["scan_pid"]) == [compile_pid]
        # The scan process shares the interpreter a fifth of its period at a time (realtime.py).
        fifth_ms = min(5.0, max(0.05, status["period_us"] / 5000))
        assert status["realtime"].endswith(f"interpreter switch interval {fifth_ms:g} ms")


def test_every_service_name_fits_linux_comm() -> None:
    """Linux keeps COMM_BYTES of a name: a longer one would show cut (softplc-modbustls
    showed as softplc-modbust)."""
    assert all(len(name.encode()) <= COMM_BYTES for name, _ in _TITLES.values())
