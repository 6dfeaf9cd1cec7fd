"""Fixtures of the security tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from softplc.security import signing
from softplc.security.programgate import ProgramGate


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    """Engineers' key pairs (NAME.key, NAME.pub) of alice, bob and mallory in tmp/keys."""
    directory = tmp_path / "keys"
    for name in ("alice", "bob", "mallory"):
        signing.new_key_pair(directory, name)
    return directory


@pytest.fixture
def gate(keys: Path, tmp_path: Path) -> ProgramGate:
    """A program gate trusting alice's key, with its state directory."""
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted)
    (tmp_path / "state").mkdir()
    return ProgramGate(tmp_path / "state", trusted)
