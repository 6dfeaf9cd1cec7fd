"""The program gate (security/programgate.py, issue 38 items 3 and 4): trusted keys read by
content at every download, and closed once signatures were asked for."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from softplc.security import signing
from softplc.security.programgate import ProgramGate, ProgramRefused

BODY = b"places: {p: 1}\n"


def signed(keys: Path, name: str) -> str:
    return signing.sign(BODY, signing.load_private(keys / f"{name}.key"))


def test_a_key_replaced_in_place_acts_at_the_next_download(keys: Path, tmp_path: Path) -> None:
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted / "plant.pub")
    gate = ProgramGate(tmp_path, trusted)
    assert gate.admit(BODY, signed(keys, "alice")) == "plant"
    info = trusted.stat()
    # bob's key written over alice's in place: same name, directory mtime kept as it was
    (trusted / "plant.pub").write_bytes((keys / "bob.pub").read_bytes())
    os.utime(trusted, ns=(info.st_atime_ns, info.st_mtime_ns))
    with pytest.raises(ProgramRefused, match="does not trust"):
        gate.admit(BODY, signed(keys, "alice"))
    assert gate.admit(BODY, signed(keys, "bob")) == "plant"


def test_an_emptied_or_removed_directory_keeps_refusing(keys: Path, tmp_path: Path) -> None:
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted)
    gate = ProgramGate(tmp_path, trusted)
    assert gate.admit(BODY, signed(keys, "alice")) == "alice"
    (trusted / "alice.pub").unlink()
    with pytest.raises(ProgramRefused, match=r"no trusted key can be read.*none there"):
        gate.admit(BODY, None)
    assert gate.keys().status()["problem"] is not None
    trusted.rmdir()
    with pytest.raises(ProgramRefused, match="no trusted key can be read"):
        gate.admit(BODY, None)
    trusted.mkdir()
    shutil.copy(keys / "bob.pub", trusted)
    assert gate.admit(BODY, signed(keys, "bob")) == "bob"  # trusted again: open again


def test_named_on_the_command_line_an_empty_directory_refuses_from_the_start(
        tmp_path: Path) -> None:
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    with pytest.raises(ProgramRefused, match="none there"):
        ProgramGate(tmp_path, trusted, required=True).admit(BODY, None)
    assert ProgramGate(tmp_path, trusted).admit(BODY, None) is None  # never asked: open


def test_an_unversioned_signed_download_runs_as_version_0(keys: Path, tmp_path: Path) -> None:
    """Issue 43: an unversioned signature records version 0, so the next unversioned one is
    not older and a versioned one is newer."""
    from softplc.security import versions
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted)
    gate = ProgramGate(tmp_path, trusted)
    line = signed(keys, "alice")
    assert gate.admit(BODY, line) == "alice"
    assert gate.applied(BODY, line, "alice") == ""  # no version to name
    assert versions.read(tmp_path).version == 0
    assert gate.admit(BODY, line) == "alice"  # the same again: not older
    one = signing.sign(BODY, signing.load_private(keys / "alice.key"), 1)
    assert gate.applied(BODY, one, "alice") == ", version 1"
    with pytest.raises(ProgramRefused, match=r"signed version 0 \(signed without --version\) "
                       "is older than the running 1"):
        gate.admit(BODY, line)


def test_the_signers_of_the_last_64_bodies_are_remembered(keys: Path, tmp_path: Path) -> None:
    gate = ProgramGate(tmp_path, tmp_path / "trusted")
    for n in range(65):  # KEEP, 64, and one more: the oldest is forgotten
        gate.remember(b"body %d" % n, f"signer{n}")
        if n == 63:
            assert len(gate.signers()) == 64
    kept = gate.signers()
    assert len(kept) == 64 and list(kept.values()) == [f"signer{n}" for n in range(1, 65)]


def test_a_trusted_directory_that_cannot_be_read_refuses_saying_so(
        keys: Path, tmp_path: Path) -> None:
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted)
    gate = ProgramGate(tmp_path, trusted)
    assert gate.admit(BODY, signed(keys, "alice")) == "alice"
    (trusted / "broken.pub").mkdir()  # reading it fails (EISDIR), even as root
    with pytest.raises(ProgramRefused, match=r"no trusted key can be read in .* \(unreadable\)"):
        gate.admit(BODY, signed(keys, "alice"))


def test_a_version_that_cannot_be_recorded_is_said_and_logged_with_the_reason(
        keys: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    trusted = tmp_path / "trusted"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted)
    gate = ProgramGate(tmp_path, trusted)
    (tmp_path / "signed_version.json").mkdir()  # the version file cannot be written
    one = signing.sign(BODY, signing.load_private(keys / "alice.key"), 1)
    said = gate.applied(BODY, one, "alice")
    assert said == (f", version 1 (not recorded: {tmp_path / 'signed_version.json'} cannot "
                    "be written)")
    assert "cannot be written (Is a directory): version 1 is not recorded" in caplog.text
