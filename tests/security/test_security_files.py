"""Every security file a PLC reads, overwritten with garbage in turn before `softplc run`
(issue 38, item 4): one line naming the file, what is wrong and what to do; the start refused
where a service cannot start without it, else the service up and closed; never a traceback,
never a wrong cause ("is the port in use?").

The garbage is fixed bytes (not ASCII, not JSON, not PEM or DER), so a run is repeatable.
"""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from softplc.security import signing
from tests.api.helpers import call
from tests.support import free_port, stop_process

ROOT = Path(__file__).resolve().parents[2]
GARBAGE = bytes([0x8F, 0x00, 0xFF, 0x1B, 0x7F, 0xC3, 0x28])  # 7 bytes, as the probe wrote
START_S = 60.0


@dataclass(frozen=True)
class Case:
    name: str
    path: str  # relative to the state directory (or "trusted/NAME": the --trusted-keys dir)
    refused: bool  # the start is refused (else the PLC serves, closed)
    says: str  # a piece of the one line
    extra: tuple[str, ...] = ()


CASES = [
    Case("owner key", "api_token", True, "api_token is not a softplc key"),
    Case("users", "users", False, "users is unusable"),
    Case("trusted key", "trusted/alice.pub", False, "trusted key skipped"),
    Case("only trusted key", "trusted/alice.pub", False, "no usable key there"),
    Case("OPC UA key", "pki/own/key.pem", True, "the OPC UA server's key cannot be used",
         ("--opcua", "127.0.0.1:0")),
    Case("audit trail", "audit.jsonl", False, "the audit trail in"),
    Case("OPC UA trusted client", "pki/trusted/panel.der", False, "a trusted client "
         "certificate"),
    Case("signed version", "signed_version.json", False, "signed_version.json is not JSON"),
    Case("API certificate", "tls/cert.pem", True, "cert.pem", ("--tls", "on")),
]


def _run(where: Path, case: Case, port: int) -> tuple[subprocess.Popen[str], Path]:
    args = [sys.executable, "-m", "softplc.cli", "run", str(ROOT / "programs" / "transport.yaml"),
            "--start", "--api", f"127.0.0.1:{port}", "--modbus", "off", "--state-dir",
            "state", "--quiet", "--period", "10ms", "--trusted-keys", "trusted", *case.extra]
    if "--opcua" not in case.extra:
        args += ["--opcua", "off"]
    err = where / "stderr.txt"
    with err.open("w") as handle:
        proc = subprocess.Popen(args, cwd=where, stdout=subprocess.DEVNULL, stderr=handle,
                                text=True)
    return proc, err


def _until(check: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if check():
            return True
        time.sleep(0.1)
    return False


def _serving(url: str) -> bool:
    try:
        return call(url, "GET", "/healthz", timeout_s=2).status == 200
    except OSError:
        return False


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_a_garbled_security_file_is_named_in_one_line(tmp_path: Path, case: Case) -> None:
    state, trusted = tmp_path / "state", tmp_path / "trusted"
    state.mkdir(mode=0o700)
    trusted.mkdir()
    keys = tmp_path / "keys"
    signing.new_key_pair(keys, "bob")
    if case.name != "only trusted key":
        (trusted / "bob.pub").write_bytes((keys / "bob.pub").read_bytes())
    target = tmp_path / case.path if case.path.startswith("trusted/") else state / case.path
    target.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    target.write_bytes(GARBAGE)
    if case.path == "tls/cert.pem":
        (state / "tls" / "key.pem").write_bytes(GARBAGE)
    target.chmod(0o600)
    port = free_port()
    proc, err = _run(tmp_path, case, port)
    url = f"http://127.0.0.1:{port}"
    try:
        if case.refused:
            proc.wait(START_S)
            assert proc.returncode == 1
        else:
            assert _until(lambda: _serving(url) or proc.poll() is not None, START_S)
            assert proc.poll() is None, err.read_text()
    finally:
        stop_process(proc)
    said = err.read_text(encoding="utf-8", errors="replace")
    assert "Traceback" not in said and "in use" not in said, said
    lines = [line for line in said.splitlines() if case.says in line]
    assert len(lines) == 1, said
    if not case.path.startswith("trusted/") or case.name != "only trusted key":
        assert case.path.rpartition("/")[2] in lines[0], lines[0]
