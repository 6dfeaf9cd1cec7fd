"""The benchmark's live runtime leaves nothing behind: a process that starts and stops it
(recording or not) exits without tracebacks or resource-tracker warnings, and no segment of
it stays in /dev/shm. (It left the supervisor's image and board segments open: BufferError
tracebacks at garbage collection, "leaked shared_memory objects" at exit.)"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = """
import gc, os
from softplc.bench.live import LiveRuntime

def main() -> None:
    for record in (True, False):
        with LiveRuntime(period_ns=10_000_000, record=record, modbus=True, api=False) as rt:
            rt.wait_for_state("RUNNING")
        gc.collect()
    print("pid", os.getpid())

if __name__ == "__main__":
    main()
"""


def test_live_runtime_start_stop_exits_clean(tmp_path: Path) -> None:
    script = tmp_path / "live.py"
    script.write_text(SCRIPT, encoding="utf-8")
    done = subprocess.run([sys.executable, str(script)], cwd=ROOT, capture_output=True,
                          text=True, timeout=180)
    assert done.returncode == 0, done.stderr
    for sign in ("Traceback", "BufferError", "resource_tracker", "leaked"):
        assert sign not in done.stderr, done.stderr
    pid = done.stdout.split()[-1]
    assert not list(Path("/dev/shm").glob(f"softplc_{pid}_*"))
