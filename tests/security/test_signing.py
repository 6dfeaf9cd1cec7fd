"""Signed programs (issue 31, item 4): Ed25519 keys, the signature of the exact bytes sent,
and a PLC with trusted keys refusing unsigned, wrongly signed and changed downloads before
they reach the scan process, naming the signer of the running program in status; without
trusted keys unsigned downloads are taken as before. The rollback rule through the HTTP door
and the CLI (issue 38, item 6; the gate itself in test_rollback.py): a signed version older
than the running one refused unless allow_older, which the audit trail names. A real
ScanLoop and ApiServer (tests/api/conftest.py), downloads sent by the client and the CLI."""

from __future__ import annotations

import hashlib
import shutil
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient, ApiError
from softplc.api.signcmds import download_body
from softplc.runtime.loop import LoopConfig
from softplc.security import signing
from softplc.security.signing import SignatureRefused, SigningError, TrustedKeys
from tests.api.conftest import PERIOD_NS, ROOT, Plc, ScanThread, make_server
from tests.api.conftest import plc_parts as plc_parts  # a pytest fixture, reexported
from tests.support import eventually

TRANSPORT = ROOT / "programs" / "transport.yaml"


def test_a_key_pair_is_private_and_never_overwritten(keys: Path) -> None:
    assert stat.S_IMODE((keys / "alice.key").stat().st_mode) == 0o600
    with pytest.raises(SigningError, match="exists already"):
        signing.new_key_pair(keys, "alice")
    (keys / "alice.key").chmod(0o644)
    with pytest.raises(SigningError, match="readable by others"):
        signing.load_private(keys / "alice.key")


def test_only_a_trusted_key_over_the_exact_bytes_verifies(keys: Path, tmp_path: Path) -> None:
    trusted_dir = tmp_path / "trusted"
    trusted_dir.mkdir()
    shutil.copy(keys / "alice.pub", trusted_dir)
    trusted = TrustedKeys.load(trusted_dir)
    body = TRANSPORT.read_bytes()
    line = signing.sign(body, signing.load_private(keys / "alice.key"))
    assert trusted.verify(body, line) == signing.Signed("alice", 0)
    with pytest.raises(SignatureRefused, match=r"not signed by a trusted key \(trusted: alice\)"):
        trusted.verify(body, None)
    changed = body[:10] + bytes([body[10] ^ 1]) + body[11:]
    with pytest.raises(SignatureRefused, match="signature by alice does not match"):
        trusted.verify(changed, line)
    other = signing.sign(body, signing.load_private(keys / "mallory.key"))
    with pytest.raises(SignatureRefused, match=r"which this PLC does not trust \(trusted: alice"):
        trusted.verify(body, other)
    with pytest.raises(SignatureRefused, match="unreadable signature"):
        trusted.verify(body, "ed25519 nonsense")


# -- against a running PLC ----------------------------------------------------------------------

@pytest.fixture
def plc(plc_parts: Plc, tmp_path: Path) -> Iterator[tuple[ApiClient, Path]]:
    """A scan loop keeping its boot program in STATE and the service on STATE (whose
    trusted_keys the test fills); the owner's client."""
    state = tmp_path / "state"
    config = LoopConfig(root=str(ROOT), period_ns=PERIOD_NS, state_dir=str(state))
    with ScanThread(plc_parts.channel, plc_parts.writer, plc_parts.board, config), \
            make_server(plc_parts, state) as api:
        yield ApiClient(api.url, state_dir=state, timeout_s=60), state


def trust(keys: Path, state: Path, name: str) -> None:
    (state / "trusted_keys").mkdir(exist_ok=True)
    shutil.copy(keys / f"{name}.pub", state / "trusted_keys")


def refused(client: ApiClient, blob: bytes, signature: str | None) -> ApiError:
    with pytest.raises(ApiError) as caught:
        client.download_bundle(blob, signature=signature)
    assert caught.value.status == 422
    return caught.value


def test_without_trusted_keys_unsigned_downloads_are_taken(
        plc: tuple[ApiClient, Path]) -> None:
    client, _ = plc
    blob, _, _ = download_body(str(TRANSPORT))
    assert client.download_bundle(blob)["state"] == "STOPPED"
    status = eventually(lambda: (s := client.status())["program"] == "transport" and s, 30,
                        "transport loaded")
    assert status["program_signer"] is None


def test_trusted_keys_refuse_unsigned_untrusted_and_changed_downloads(
        plc: tuple[ApiClient, Path], keys: Path) -> None:
    client, state = plc
    trust(keys, state, "alice")
    blob, _, _ = download_body(str(TRANSPORT))
    error = refused(client, blob, None)
    assert error.message == "download refused: not signed by a trusted key (trusted: alice)"
    by_mallory = signing.sign(blob, signing.load_private(keys / "mallory.key"))
    assert "does not trust (trusted: alice)" in refused(client, blob, by_mallory).message
    by_alice = signing.sign(blob, signing.load_private(keys / "alice.key"))
    changed = bytearray(blob)
    changed[len(blob) // 2] ^= 0x01
    assert "does not match" in refused(client, bytes(changed), by_alice).message
    assert client.status()["program"] is None  # none of them reached the scan
    audit = [r for r in _trail(state) if r["action"] == "POST program"]
    assert [r["outcome"] for r in audit] == ["refused"] * 3


def test_a_signed_download_runs_and_status_names_its_signer(
        plc: tuple[ApiClient, Path], keys: Path) -> None:
    client, state = plc
    trust(keys, state, "alice")
    blob, _, _ = download_body(str(TRANSPORT))
    line = signing.sign(blob, signing.load_private(keys / "alice.key"))
    reply = client.download_bundle(blob, signature=line)
    assert reply["signer"] == "alice" and "signed by alice" in reply["message"]
    eventually(lambda: client.status()["program_signer"] == "alice", 30,
               "status naming the signer")
    applied = [r for r in _trail(state) if r["action"] == "POST program"][-1]
    assert applied["outcome"] == "applied" and "signed by alice" in applied["detail"]["message"]


def test_the_cli_signs_and_sends_a_signature(plc: tuple[ApiClient, Path], keys: Path,
                                             tmp_path: Path) -> None:
    client, state = plc
    trust(keys, state, "alice")
    env_key = str(keys / "alice.key")
    signed = _cli("sign", str(TRANSPORT), "--key", env_key, "-o", str(tmp_path / "t.sig"))
    assert signed.returncode == 0, signed.stderr
    unsigned = _cli("download", str(TRANSPORT), "--api", client.url, "--state-dir", str(state))
    assert unsigned.returncode == 1 and "not signed by a trusted key" in unsigned.stderr
    sent = _cli("download", str(TRANSPORT), "--api", client.url, "--state-dir", str(state),
                "--signature", str(tmp_path / "t.sig"))
    assert sent.returncode == 0, sent.stderr
    assert "signed by alice" in sent.stdout
    eventually(lambda: client.status()["program_signer"] == "alice", 30, "signer in status")


def test_an_older_signed_version_is_refused_unless_allowed_and_audited(
        plc: tuple[ApiClient, Path], keys: Path) -> None:
    client, state = plc
    trust(keys, state, "alice")
    blob, _, _ = download_body(str(TRANSPORT))
    alice = signing.load_private(keys / "alice.key")
    v1, v2 = (signing.sign(blob, alice, version) for version in (1, 2))
    assert client.download_bundle(blob, signature=v2)["message"].endswith(
        "(signed by alice, version 2)")
    error = refused(client, blob, v1)  # a captured older program, sent again
    assert error.message == ("download refused: signed version 1 is older than the running 2 "
                             "(an engineer may pass --allow-older)")
    assert client.download_bundle(blob, signature=v2)["signer"] == "alice"  # the same again
    back = client.download_bundle(blob, signature=v1, allow_older=True)
    assert back["message"].endswith("(signed by alice, version 1, rolled back from 2 "
                                    "(allow older))")
    records = [r for r in _trail(state) if r["action"] == "POST program"]
    assert [r["outcome"] for r in records] == ["applied", "refused", "applied", "applied"]
    assert records[-1]["detail"]["allow_older"] == "true"
    assert records[-1]["detail"]["body_sha256"] == hashlib.sha256(blob).hexdigest()
    assert "rolled back from 2" in records[-1]["detail"]["message"]
    assert "older than the running 2" in records[1]["detail"]["message"]


def test_the_cli_signs_a_version_and_allows_an_older_one(
        plc: tuple[ApiClient, Path], keys: Path, tmp_path: Path) -> None:
    client, state = plc
    trust(keys, state, "alice")
    key, sig = str(keys / "alice.key"), str(tmp_path / "t.sig")
    signed = _cli("sign", str(TRANSPORT), "--key", key, "--version", "7", "-o", sig)
    assert signed.returncode == 0 and "version 7" in signed.stdout, signed.stderr
    assert Path(sig).read_text().strip().endswith(" version=7")
    connect = ("--api", client.url, "--state-dir", str(state))
    sent = _cli("download", str(TRANSPORT), *connect, "--signature", sig)
    assert sent.returncode == 0 and "version 7" in sent.stdout, sent.stderr
    older = ("download", str(TRANSPORT), *connect, "--sign-key", key, "--version", "6")
    refused_older = _cli(*older)
    assert refused_older.returncode == 1
    assert "signed version 6 is older than the running 7" in refused_older.stderr
    allowed = _cli(*older, "--allow-older")
    assert allowed.returncode == 0, allowed.stderr
    assert "rolled back from 7" in allowed.stdout


def _cli(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *argv], capture_output=True,
                          text=True, timeout=120, cwd=ROOT)


def _trail(state: Path) -> list[dict[str, Any]]:
    from softplc.security.audit import AuditTrail

    return list(AuditTrail(state).records(None, 1000))


# -- the signing helpers in-process (issue 43: signing.py's own fast tests in `make mutate`) ----

def test_signing_helpers_version_limit_is_eighteen_digits(keys: Path, tmp_path: Path) -> None:
    key = signing.load_private(keys / "alice.key")
    trusted = TrustedKeys.load(keys)  # alice, bob, mallory: the .pub files only
    body = b"program"
    top = 999_999_999_999_999_999  # MAX_VERSION, written out: a moved limit fails here
    line = signing.sign(body, key, top)
    assert line.endswith(f" version={top}") and top == signing.MAX_VERSION
    assert trusted.verify(body, line) == signing.Signed("alice", top)
    assert signing.Signature.parse(line).version == top
    for bad in (top + 1, -1):
        with pytest.raises(SigningError, match=f"version {bad}: a whole number from 0 to {top}"):
            signing.sign(body, key, bad)
    assert trusted.verify(body, signing.sign(body, key, 0)) == signing.Signed("alice", 0)
    edited = signing.sign(body, key, 7).replace("version=7", "version=8")
    with pytest.raises(SignatureRefused, match="signature by alice does not match"):
        trusted.verify(body, edited)


def test_signing_helpers_trust_at_most_256_keys(keys: Path, tmp_path: Path) -> None:
    public = (keys / "alice.pub").read_bytes()
    for count in (256, 257):  # MAX_KEYS exactly, and one over: the first 256 by name
        directory = tmp_path / f"trusted{count}"
        directory.mkdir()
        for n in range(count):
            (directory / f"k{n:03d}.pub").write_bytes(public)
        trusted = TrustedKeys.load(directory)
        assert trusted.names == [f"k{n:03d}" for n in range(256)], count
        assert trusted.problems == ()


def test_signing_helpers_key_names_and_files(tmp_path: Path) -> None:
    assert signing.check_name("alice-2_b") == "alice-2_b"
    for bad in ("Bad Name", "2alice", "", "a" * 33):
        with pytest.raises(SigningError, match="1 to 32 of a-z 0-9 _ -, starting with a letter"):
            signing.check_name(bad)
    directory = tmp_path / "new"
    assert signing.new_key_pair(directory, "carol") == (directory / "carol.key",
                                                        directory / "carol.pub")
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700
    with pytest.raises(SigningError, match="key name 'Carol'"):
        signing.new_key_pair(directory, "Carol")
    assert sorted(p.name for p in directory.iterdir()) == ["carol.key", "carol.pub"]
    public = signing.load_public(directory / "carol.pub")
    assert signing.fingerprint(public) == signing.fingerprint(
        signing.load_private(directory / "carol.key").public_key())


def test_signing_helpers_refuse_unusable_key_files(keys: Path, tmp_path: Path) -> None:
    garbled = tmp_path / "garbled.key"
    garbled.write_bytes(b"-----BEGIN PRIVATE KEY-----\nnot a key\n-----END PRIVATE KEY-----\n")
    garbled.chmod(0o600)
    with pytest.raises(SigningError, match=r"garbled.key: not an unencrypted PEM private key"):
        signing.load_private(garbled)
    with pytest.raises(SigningError, match=r"missing.key: No such file"):
        signing.load_private(tmp_path / "missing.key")
    with pytest.raises(SigningError, match="not a PEM public key"):
        signing.load_public(garbled)
    with pytest.raises(SigningError, match=r"missing.pub: No such file"):
        signing.load_public(tmp_path / "missing.pub")
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    other = ec.generate_private_key(ec.SECP256R1())
    ecdsa = tmp_path / "ecdsa.key"
    ecdsa.write_bytes(other.private_bytes(serialization.Encoding.PEM,
                                          serialization.PrivateFormat.PKCS8,
                                          serialization.NoEncryption()))
    ecdsa.chmod(0o600)
    with pytest.raises(SigningError, match=r"ecdsa\.key: not an Ed25519 key"):
        signing.load_private(ecdsa)
    ecdsa_pub = tmp_path / "trusted" / "ecdsa.pub"
    ecdsa_pub.parent.mkdir()
    ecdsa_pub.write_bytes(other.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo))
    with pytest.raises(SigningError, match=r"ecdsa\.pub: not an Ed25519 public key"):
        signing.load_public(ecdsa_pub)
    shutil.copy(keys / "bob.pub", ecdsa_pub.parent)
    trusted = TrustedKeys.load(ecdsa_pub.parent)
    assert trusted.names == ["bob"] and len(trusted.problems) == 1
    assert "ecdsa.pub: not an Ed25519 public key" in trusted.problems[0]
    assert TrustedKeys.load(tmp_path / "nowhere") == TrustedKeys()
    with pytest.raises(SigningError, match="not a softplc signature"):
        signing.Signature.parse("ed25519 SHA256:x y")
