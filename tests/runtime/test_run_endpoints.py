"""Where a real `softplc run` serves and how clients find it (issue 40, item 4): the API on
an IPv6 loopback address (`--api [::1]:PORT`; before, the start refused it), client commands
that take their URL from $SOFTPLC_API (an explicit --api wins), and the banner's `try:` line
for an HTTPS API that works when pasted into a shell (before, it had no --cacert and curl
refused the self-signed certificate)."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

from softplc.api.client import ApiClient
from softplc.cli.argtypes import endpoint
from softplc.runtime.supervise.runcmd import host_port, try_api
from tests.support import free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
QUIET_RUN = ("--start", "--quiet", "--modbus", "off", "--opcua", "off", "--state-dir", "state",
             "--watchdog", "100", "--on-stall", "continue")


def free_ipv6_port() -> int | None:
    """A port free on ::1 a moment ago; None when this machine has no IPv6 loopback."""
    if not socket.has_ipv6:
        return None
    try:
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
            return int(probe.getsockname()[1])
    except OSError:
        return None


@pytest.mark.parametrize(("text", "bound"), [
    ("[::1]:8080", ("::1", 8080)), ("[::]:502", ("::", 502)), ("127.0.0.1:5020",
                                                                ("127.0.0.1", 5020)),
    (":8080", ("127.0.0.1", 8080)), ("off", None)])
def test_host_port_as_written_and_as_bound(text: str, bound: tuple[str, int] | None) -> None:
    assert endpoint(text) == bound
    if bound is not None and text.startswith(("[", "1")):
        assert host_port(*bound) == text


@pytest.mark.parametrize("text", ["[::1]", "::1]:80", "[::1:80", "localhost"])
def test_a_malformed_endpoint_is_refused(text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError):
        endpoint(text)


def test_the_try_line_asks_a_wildcard_bind_on_loopback_with_the_owners_key() -> None:
    args = argparse.Namespace(api=("::", 8443), api_scheme="https", api_cert="/s/tls/cert.pem",
                              state_dir="/s")
    assert try_api(args) == ["curl", "-sS", "--cacert", "/s/tls/cert.pem", "-H",
                             "Authorization: Bearer $(cat /s/api_token)",
                             "https://[::1]:8443/api/v1/status"]
    args = argparse.Namespace(api=("::1", 8080), state_dir="/s")
    assert try_api(args) == ["curl", "-sS", "http://[::1]:8080/api/v1/status"]


def softplc(*argv: str, cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "softplc.cli", *argv], cwd=cwd,
                          capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(ROOT), **env})


def banner_line(proc: subprocess.Popen[str], text: str) -> str:
    """The banner's line holding `text` (it is printed once every service serves)."""
    assert proc.stdout is not None
    for line in proc.stdout:
        if text in line:
            return line.strip()
    raise AssertionError(f"softplc run ended without a banner line with {text!r}")


def test_api_on_ipv6_loopback_and_client_url_from_environment(tmp_path: Path) -> None:
    port = free_ipv6_port()
    if port is None:
        pytest.skip("no IPv6 loopback on this machine")
    url = f"http://[::1]:{port}"
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--api", f"[::1]:{port}",
                      *QUIET_RUN], lambda: ApiClient(url, timeout_s=5).status(),
                     cwd=tmp_path, what="softplc run answering on [::1]") as proc:
        assert f"HTTP API on {url};" in banner_line(proc, "HTTP API on")
        with urllib.request.urlopen(f"{url}/healthz", timeout=5) as answer:
            assert json.load(answer) == {"status": "ok"}
        from_env = softplc("status", "--json", cwd=tmp_path, env={"SOFTPLC_API": url})
        assert from_env.returncode == 0, from_env.stderr
        assert json.loads(from_env.stdout)["state"] == "RUNNING"
        elsewhere = f"http://127.0.0.1:{free_port()}"
        explicit = softplc("status", "--api", elsewhere, cwd=tmp_path,
                           env={"SOFTPLC_API": url})
        assert explicit.returncode == 2, explicit.stdout  # nothing answers there: --api won


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_tls_banner_try_line_works_as_printed(tmp_path: Path) -> None:
    port = free_port()
    cert = tmp_path / "state" / "tls" / "cert.pem"
    with softplc_run([str(ROOT / "programs" / "transport.yaml"), "--api", f"127.0.0.1:{port}",
                      "--tls", "on", *QUIET_RUN],
                     lambda: cert.exists() and ApiClient(f"https://127.0.0.1:{port}", ca=cert,
                                                         timeout_s=5).status(),
                     cwd=tmp_path, what="softplc run answering over https") as proc:
        line = banner_line(proc, "HTTP API on")
        command = line.split("try: ", 1)[1]
        # Pasted into a shell elsewhere than the PLC's working directory.
        pasted = subprocess.run(["sh", "-c", command], cwd="/", capture_output=True,
                                text=True, timeout=30)
        assert pasted.returncode == 0, f"{command}: {pasted.stderr}"
        assert json.loads(pasted.stdout)["state"] == "RUNNING"
