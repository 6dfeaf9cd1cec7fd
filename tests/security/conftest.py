"""Fixtures of the security tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.security import signing


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    """Engineers' key pairs (NAME.key, NAME.pub) of alice, bob and mallory in tmp/keys."""
    directory = tmp_path / "keys"
    for name in ("alice", "bob", "mallory"):
        signing.new_key_pair(directory, name)
    return directory
