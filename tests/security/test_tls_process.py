"""HTTPS (issue 31, item 2) against a real `softplc run --tls on` on a fresh state directory:
the certificate made at the first start, Debian's curl with it as CA (login, a viewer's stop
refused, an operator's stop applied, the session cookie Secure), `openssl s_client` refused
with TLS 1.1 and accepted with TLS 1.2, and softplc's own client and CLI verifying the
server (the owner's CLI by the state directory; a wrong CA refused); signed downloads over
HTTPS to a PLC given --trusted-keys."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api.client import ApiClient, ApiUnreachable
from softplc.security import signing, tls
from tests.support import eventually, free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
PASSWORDS = {"op": "operator-pass-1", "view": "viewer-pass-1"}
CURL = shutil.which("curl")
OPENSSL = shutil.which("openssl")


def softplc(*argv: str, cwd: Path, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *argv], cwd=cwd, input=stdin,
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, Path, Path]]:
    """(https URL, working directory, the generated certificate)."""
    where = tmp_path_factory.mktemp("tls")
    for name, role in (("op", "operator"), ("view", "viewer")):
        added = softplc("users", "add", name, "--role", role, "--state-dir", "state",
                        cwd=where, stdin=PASSWORDS[name] + "\n")
        assert added.returncode == 0, added.stderr
    signing.new_key_pair(where / "keys", "alice")
    (where / "trusted").mkdir()
    shutil.copy(where / "keys" / "alice.pub", where / "trusted")
    port = free_port()
    url, cert = f"https://127.0.0.1:{port}", where / "state" / "tls" / "cert.pem"
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--start", "--api",
                      f"127.0.0.1:{port}", "--tls", "on", "--modbus", "off", "--opcua", "off",
                      "--state-dir", "state", "--quiet", "--period", "10ms", "--trusted-keys",
                      "trusted"],
                     lambda: cert.exists() and ApiClient(url, ca=cert, timeout_s=5).status()[
                         "state"] == "RUNNING",
                     cwd=where, what="softplc run answering over https and RUNNING"):
        yield url, where, cert


def curl(cert: Path, *argv: str) -> tuple[int, str, str]:
    """(HTTP status, body, headers) of one curl call that verifies against `cert`."""
    assert CURL is not None
    done = subprocess.run([CURL, "-sS", "--cacert", str(cert), "-D", "-", "-o", "/dev/stderr",
                           "-w", "%{http_code}", *argv], capture_output=True, text=True,
                          timeout=60)
    headers, _, code = done.stdout.rpartition("\n\n")  # text mode: \r\n read as \n
    return int(code or 0), done.stderr, headers


@pytest.mark.skipif(CURL is None, reason="Debian's curl is not installed (.ci/run installs it)")
def test_curl_over_https_login_roles_and_a_secure_cookie(plc: tuple[str, Path, Path],
                                                         tmp_path: Path) -> None:
    url, where, cert = plc
    jar = tmp_path / "view.jar"
    code, body, headers = curl(cert, "-c", str(jar), "-H", "Content-Type: application/json",
                               "-d", json.dumps({"user": "view", "password": PASSWORDS["view"]}),
                               f"{url}/api/v1/login")
    assert code == 200, body
    cookie = next(h for h in headers.splitlines() if h.lower().startswith("set-cookie:"))
    assert "Secure" in cookie and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    code, body, _ = curl(cert, "-b", str(jar), "-X", "POST", f"{url}/api/v1/stop")
    assert code == 403 and "needs operator" in body
    code, body, _ = curl(cert, "-u", f"op:{PASSWORDS['op']}", "-X", "POST", f"{url}/api/v1/stop")
    assert code == 200 and json.loads(body)["state"] == "STOPPED", body
    code, body, _ = curl(cert, f"{url}/api/v1/status")  # loopback without credentials: viewer
    assert code == 200 and json.loads(body)["state"] == "STOPPED"
    trail = [json.loads(line) for line in softplc(
        "audit", "--json", "--state-dir", "state", cwd=where).stdout.splitlines()]
    stops = [(r["user"], r["outcome"]) for r in trail if r["action"] == "POST stop"]
    assert stops[-2:] == [("view", "denied"), ("op", "applied")]
    assert curl(cert, "-u", f"op:{PASSWORDS['op']}", "-X", "POST",
                f"{url}/api/v1/resume")[0] == 200
    plain = subprocess.run([str(CURL), "-sS", "-o", "/dev/null", "-w", "%{http_code}",
                            url.replace("https", "http") + "/api/v1/status"],
                           capture_output=True, text=True, timeout=60)
    assert plain.stdout in ("000", ""), "plain HTTP must get no answer from the TLS port"


@pytest.mark.skipif(OPENSSL is None, reason="Debian's openssl is not installed")
def test_openssl_s_client_gets_tls_1_2_and_never_1_1(plc: tuple[str, Path, Path]) -> None:
    url, _, cert = plc
    where = url.removeprefix("https://")
    assert OPENSSL is not None

    def s_client(*flags: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([OPENSSL, "s_client", "-connect", where, "-CAfile", str(cert),
                               *flags], input="", capture_output=True, text=True, timeout=60)

    # SECLEVEL=0: this client offers TLS 1.1 itself; the server must be the one to refuse.
    old = s_client("-tls1_1", "-cipher", "DEFAULT:@SECLEVEL=0")
    assert old.returncode != 0 and "Cipher is (NONE)" in old.stdout, old.stdout
    new = s_client("-tls1_2")
    assert new.returncode == 0, new.stdout + new.stderr
    assert "Protocol  : TLSv1.2" in new.stdout and "Verify return code: 0 (ok)" in new.stdout
    modern = s_client("-tls1_3")
    assert modern.returncode == 0 and "TLSv1.3" in modern.stdout


def test_softplc_clients_verify_the_plc(plc: tuple[str, Path, Path], tmp_path: Path) -> None:
    url, where, cert = plc
    owner = ApiClient(url, state_dir=where / "state")  # its certificate found there
    assert owner.ca == cert and owner.whoami()["user"] == "owner"
    stranger = tmp_path / "other.pem"
    stranger.write_bytes(tls._self_signed("127.0.0.1")[0])
    with pytest.raises(ApiUnreachable, match="CERTIFICATE_VERIFY_FAILED"):
        ApiClient(url, ca=stranger, timeout_s=5).status()
    status = softplc("status", "--api", url, "--state-dir", "state", cwd=where)
    assert status.returncode == 0 and "state" in status.stdout, status.stderr
    wrong = softplc("status", "--api", url, "--ca", str(stranger), "--timeout", "5", cwd=where)
    assert wrong.returncode == 2 and "CERTIFICATE_VERIFY_FAILED" in wrong.stderr


def test_the_mode_decides_by_the_bind_and_the_pin_rule(tmp_path: Path) -> None:
    auto, on, off = tls.TlsSettings("auto"), tls.TlsSettings("on"), tls.TlsSettings("off")
    assert not auto.wanted("127.0.0.1") and auto.wanted("0.0.0.0") and auto.wanted("10.0.0.7")
    assert on.wanted("127.0.0.1") and not off.wanted("0.0.0.0")
    cert, key, made = tls.certificate(auto, tmp_path, "0.0.0.0")
    assert made and oct(key.stat().st_mode & 0o777) == "0o600"
    assert tls.certificate(auto, tmp_path, "0.0.0.0")[2] is False  # made once, reused
    context = tls.server_context(cert, key)
    assert context.minimum_version.name == "TLSv1_2"
    assert tls.client_context(cert).check_hostname is False  # a pinned self-signed leaf
    assert tls.client_context(None).check_hostname is True
    started = time.monotonic()
    refused = softplc("run", "--tls-cert", str(cert), "--state-dir", str(tmp_path / "s"),
                      "--api", "127.0.0.1:0", "--modbus", "off", "--opcua", "off",
                      "--duration", "1s", cwd=tmp_path)
    assert refused.returncode == 1 and "--tls-cert and --tls-key go together" in refused.stderr
    assert time.monotonic() - started < 60


def test_signed_downloads_over_https_with_trusted_keys(plc: tuple[str, Path, Path]) -> None:
    url, where, _ = plc
    program = str(ROOT / "programs" / "transport.yaml")
    owner = ("--api", url, "--state-dir", "state")
    assert softplc("stop", *owner, cwd=where).returncode == 0
    unsigned = softplc("download", program, *owner, cwd=where)
    assert unsigned.returncode == 1
    assert "not signed by a trusted key (trusted: alice)" in unsigned.stderr
    signed = softplc("download", program, *owner, "--sign-key", "keys/alice.key", cwd=where)
    assert signed.returncode == 0 and "signed by alice" in signed.stdout, signed.stderr
    client = ApiClient(url, state_dir=where / "state")
    eventually(lambda: client.status()["program_signer"] == "alice", 30, "the signer in status")
