"""The state directory is private (issue 26.4): it holds the API token and the program's
state, so `softplc run` creates it 0700 and tightens an existing one of this user's to 0700;
one it may not tighten (another user's) is said in status and on stderr, and left alone."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from softplc.runtime.retain.writer import RetainStore, RetainWriter, check_state_dir

ROOT = Path(__file__).resolve().parents[2]
NOBODY = 65534


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def softplc_run(state: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml", "--start",
         "--modbus", "off", "--api", "off", "--opcua", "off", "--state-dir", str(state),
         "--quiet", "--duration", "300ms"],
        cwd=ROOT, capture_output=True, text=True, timeout=120)


@pytest.fixture
def loose_umask() -> object:
    old = os.umask(0o022)  # the usual umask: a plain mkdir gives 0755
    yield None
    os.umask(old)


def test_softplc_run_creates_the_state_directory_0700(tmp_path: Path, loose_umask: object) -> None:
    state = tmp_path / "new" / "state"
    done = softplc_run(state)
    assert done.returncode == 0, done.stderr
    assert mode(state) == 0o700
    assert "warning" not in done.stderr


def test_softplc_run_tightens_an_existing_state_directory(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    state.chmod(0o755)
    done = softplc_run(state)
    assert done.returncode == 0, done.stderr
    assert mode(state) == 0o700
    assert "warning" not in done.stderr


def test_the_store_and_the_check_make_it_private(tmp_path: Path, loose_umask: object) -> None:
    fresh = tmp_path / "fresh"
    assert check_state_dir(fresh) == ""  # the command line's check runs first: it creates it
    assert mode(fresh) == 0o700
    open_one = tmp_path / "open"
    open_one.mkdir(mode=0o775)
    open_one.chmod(0o775)
    writer = RetainWriter(RetainStore.open(open_one))
    try:
        assert mode(open_one) == 0o700
        assert writer.info()["dir_note"] == ""
    finally:
        writer.close()


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give the directory away")
def test_another_users_directory_is_left_alone_and_said(tmp_path: Path) -> None:
    state = tmp_path / "state"
    state.mkdir()
    state.chmod(0o755)
    os.chown(state, NOBODY, NOBODY)
    note = check_state_dir(state)
    assert f"owned by uid {NOBODY}" in note and "not tightened" in note
    writer = RetainWriter(RetainStore.open(state))
    try:
        assert writer.info()["dir_note"] == note  # status: retain.dir_note
    finally:
        writer.close()
    assert mode(state) == 0o755  # not ours to change
    done = softplc_run(state)
    assert done.returncode == 0, done.stderr
    assert f"softplc: warning: {note}" in done.stderr
    assert mode(state) == 0o755
