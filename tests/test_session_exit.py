"""pytest (with tests/conftest.py) exits after its summary even when a test leaves a
non-daemon thread blocked forever or a multiprocessing child running; the status is pytest's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LEAKY = '''
import multiprocessing, threading, time

def test_leaves_a_thread_and_a_child_behind():
    threading.Thread(target=threading.Event().wait, name="stuck-forever").start()
    multiprocessing.get_context("spawn").Process(target=time.sleep, args=(3600,),
                                                 name="sleeping-child").start()

def test_fails():
    assert {outcome}
'''


def run_leaky(tmp_path: Path, outcome: str) -> subprocess.CompletedProcess[str]:
    test = tmp_path / "test_leaky.py"
    test.write_text(LEAKY.format(outcome=outcome), encoding="utf-8")
    # Without the hooks this never ends (the thread waits forever): the timeout is a guard.
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "tests.conftest", "-p", "no:cacheprovider",
         "--rootdir", str(tmp_path), str(test)],
        cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_pytest_exits_with_its_status_despite_what_tests_left_running(tmp_path: Path) -> None:
    run = run_leaky(tmp_path, "False")  # a failure too: the status must be pytest's (1)
    assert run.returncode == 1 and "1 failed, 1 passed" in run.stdout, run.stdout + run.stderr
    assert "process sleeping-child" in run.stderr and "thread stuck-forever" in run.stderr
