"""The rollback rule of signed programs (issue 38, item 6): a version signed with the bytes,
a signed version older than the running one refused unless an engineer allows it, the same or
a newer one taken, the running version raised only by what the PLC took, and a corrupt
version file refusing closed with one line naming it. The gate in-process, OPC UA's Download
arguments in-process; the HTTP door and the CLI in tests/security/test_signing.py."""

from __future__ import annotations

import asyncio
import stat
from pathlib import Path

import pytest
from asyncua import ua

from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import CommandReply, CommandRequest, HmiWrite
from softplc.opcua.program import Outcome, ProgramHandling
from softplc.security import signing, versions
from softplc.security.programgate import ProgramGate, ProgramRefused
from softplc.security.signing import SignatureRefused

BODY = b"places: {p: 1}\n"


def line(keys: Path, version: int | None, body: bytes = BODY) -> str:
    return signing.sign(body, signing.load_private(keys / "alice.key"), version)


def take(gate: ProgramGate, signature: str, allow_older: bool = False) -> str:
    """What a door does with a download the PLC takes: admit, then applied."""
    signer = gate.admit(BODY, signature, allow_older)
    assert signer == "alice"
    return gate.applied(BODY, signature, signer, allow_older)


def test_the_version_is_signed_with_the_bytes(keys: Path, gate: ProgramGate) -> None:
    trusted = gate.keys().keys
    v3 = line(keys, 3)
    assert v3.endswith(" version=3")
    assert trusted.verify(BODY, v3) == signing.Signed("alice", 3)
    assert trusted.verify(BODY, line(keys, None)) == signing.Signed("alice", 0)  # as before
    for edited in (v3.replace("version=3", "version=9"), v3.removesuffix(" version=3"),
                   line(keys, None) + " version=7"):
        with pytest.raises(SignatureRefused, match="does not match"):
            trusted.verify(BODY, edited)
    for malformed in ("version=03", "version=-1", "version=1e3", "version="):
        with pytest.raises(SignatureRefused, match="unreadable signature"):
            trusted.verify(BODY, v3.replace("version=3", malformed))
    with pytest.raises(signing.SigningError, match="whole number"):
        line(keys, -1)


def test_an_older_signed_version_is_refused_unless_an_engineer_allows_it(
        keys: Path, gate: ProgramGate) -> None:
    assert take(gate, line(keys, 5)) == ", version 5"
    with pytest.raises(ProgramRefused) as refused:
        gate.admit(BODY, line(keys, 3))
    assert refused.value.reason == ("download refused: signed version 3 is older than the "
                                    "running 5 (an engineer may pass --allow-older)")
    with pytest.raises(ProgramRefused, match=r"version 0 \(signed without --version\) is old"):
        gate.admit(BODY, line(keys, None))  # an old unversioned signature is version 0
    assert take(gate, line(keys, 5)) == ", version 5"  # the running one again: taken
    assert take(gate, line(keys, 3), allow_older=True) == \
        ", version 3, rolled back from 5 (allow older)"
    assert take(gate, line(keys, 4)) == ", version 4"  # newer than the running 3
    state = gate.state_dir / versions.VERSION_FILE
    assert stat.S_IMODE(state.stat().st_mode) == 0o600
    assert versions.read(gate.state_dir) == versions.Running(4)


def test_only_what_the_plc_took_raises_the_running_version(
        keys: Path, gate: ProgramGate) -> None:
    take(gate, line(keys, 5))
    assert gate.admit(BODY, line(keys, 7)) == "alice"  # admitted, then refused by the PLC
    assert gate.admit(BODY, line(keys, 5)) == "alice"  # so 5 still runs and is taken
    take(gate, line(keys, 7))
    with pytest.raises(ProgramRefused, match="older than the running 7"):
        gate.admit(BODY, line(keys, 6))


def test_without_trusted_keys_versions_are_not_asked_for(keys: Path, tmp_path: Path) -> None:
    open_gate = ProgramGate(tmp_path / "state", tmp_path / "none")
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / versions.VERSION_FILE).write_text('{"version": 9}')
    assert open_gate.admit(BODY, line(keys, 1)) is None  # a signature sent is ignored


@pytest.mark.parametrize("garbage", [b"\x8f\x01\xfe\x00\x17\xc3\x9a", b"{}", b'{"version": -2}',
                                     b"[" * 4000, b"[" * 5000, b""])
def test_a_corrupt_version_file_refuses_closed_naming_it(
        keys: Path, gate: ProgramGate, garbage: bytes) -> None:
    take(gate, line(keys, 2))
    path = gate.state_dir / versions.VERSION_FILE
    path.write_bytes(garbage)
    with pytest.raises(ProgramRefused) as refused:
        gate.admit(BODY, line(keys, 9))  # even a newer one: the running version is unknown
    assert str(path) in refused.value.reason and "--allow-older" in refused.value.reason
    assert "\n" not in refused.value.reason
    assert take(gate, line(keys, 9), allow_older=True) == \
        ", version 9 (allow older: the running version was unknown)"
    with pytest.raises(ProgramRefused, match="older than the running 9"):  # written anew
        gate.admit(BODY, line(keys, 2))


def test_an_unreadable_version_file_refuses_closed(keys: Path, gate: ProgramGate) -> None:
    take(gate, line(keys, 2))
    path = gate.state_dir / versions.VERSION_FILE
    path.unlink()
    path.mkdir()  # EISDIR: read as root too, unlike a chmod 000
    with pytest.raises(ProgramRefused, match=f"{path} is unreadable"):
        gate.admit(BODY, line(keys, 3))
    # allowed, and taken by the PLC: the version cannot be written, and the answer says so
    assert take(gate, line(keys, 3), allow_older=True) == \
        f", version 3 (not recorded: {path} cannot be written)"


# -- OPC UA Download's AllowOlder argument (the gate behind it as above) -------------------------

class _Channel:
    def __init__(self) -> None:
        self.sent: list[CommandRequest] = []

    def send_command(self, request: CommandRequest, timeout_s: float = 0) -> CommandReply:
        self.sent.append(request)
        return CommandReply(request.id, True, "download: now STOPPED", PlcState.STOPPED)

    def send_hmi_write(self, write: HmiWrite) -> None:
        raise AssertionError("no writes here")


def test_opcua_download_refuses_an_older_version_unless_allow_older(
        keys: Path, gate: ProgramGate) -> None:
    channel, heard = _Channel(), []

    async def on_outcome(method: str, outcome: Outcome) -> None:
        heard.append(outcome)

    async def download(version: int, *more: object) -> ua.CallMethodResult:
        args = [BODY.decode(), False, "p.yaml", line(keys, version), *more]
        return await handling.call("Download", [ua.Variant(a) for a in args])

    handling = ProgramHandling(channel, on_outcome, gate)
    assert asyncio.run(download(5)).StatusCode.is_good()
    refused = asyncio.run(download(3))
    assert refused.StatusCode.value == ua.StatusCodes.BadSecurityChecksFailed
    assert "signed version 3 is older than the running 5" in heard[-1].message
    assert len(channel.sent) == 1  # the older one never reached the scan
    assert asyncio.run(download(3, True)).StatusCode.is_good()
    # the audit record carries the method's Message: the rollback is named there
    assert heard[-1].message.endswith("(signed by alice, version 3, rolled back from 5 "
                                      "(allow older))")
    mismatch = asyncio.run(download(3, "yes"))
    assert mismatch.StatusCode.value == ua.StatusCodes.BadTypeMismatch
