"""The client's plain-http transport (api/plainhttp.py, issue 40): against the real API server
(IPv4 and an IPv6 literal, answers and error statuses, a binary body, `softplc status --json`
in a fresh interpreter importing no urllib.request, http.client or email), and against a
one-connection socket server on 127.0.0.1 sending what aiohttp does not: a chunked body, a
body cut short, no answer at all, no HTTP, silence."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api import plainhttp
from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.program import bundle
from tests.api.conftest import Plc, ScanThread, ServerThread, make_server
from tests.api.helpers import BAD_PROGRAM, TRANSPORT
from tests.test_cli_imports import WRAPPER

ROOT = Path(__file__).resolve().parents[2]
URLLIB = {"urllib.request", "http.client", "http", "email", "ssl"}


def test_the_client_against_the_real_server(api: ServerThread) -> None:
    client = ApiClient(api.url, timeout_s=30)
    assert client.status()["state"] == "EMPTY"
    with pytest.raises(ApiError) as refused:
        client.stop()
    assert refused.value.status == 409 and "EMPTY" in refused.value.message
    with pytest.raises(ApiError) as bad:
        client.download_text(BAD_PROGRAM, name="my_broken.yaml")
    assert bad.value.status == 422 and all("my_broken.yaml:" in p for p in bad.value.problems)
    blob = bundle.pack(bundle.from_files(TRANSPORT))
    assert client.download_bundle(blob)["state"] == "STOPPED"  # a binary body sent
    with pytest.raises(ApiError) as unknown:
        client.symbol("no_such_symbol")
    assert unknown.value.status == 404
    answer = plainhttp.request(api.url + "/api/v1/status?x=1", "GET", {}, None, 10)
    with answer:
        assert answer.status == 200 and "content-length" in answer.headers
        assert json.loads(answer.read())["state"] == "STOPPED"


def test_status_json_from_a_fresh_interpreter_imports_no_urllib(api: ServerThread) -> None:
    done = subprocess.run([sys.executable, "-c", WRAPPER, "status", "--json", "--api", api.url],
                          cwd=ROOT, text=True, capture_output=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["state"] == "EMPTY"
    modules = set(json.loads(done.stderr.splitlines()[-1]))
    assert not modules & URLLIB, sorted(modules & URLLIB)


def ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as sock:
            sock.bind(("::1", 0))
    except OSError:
        return False
    return True


@pytest.mark.skipif(not ipv6_loopback(), reason="no IPv6 loopback here")
def test_an_ipv6_literal(plc_parts: Plc, scan: ScanThread, tmp_path: Path) -> None:
    with make_server(plc_parts, tmp_path / "state", host="::1") as handle:
        client = ApiClient(f"http://[::1]:{handle.server.bound_port}", timeout_s=30)
        assert client.status()["state"] == "EMPTY"
        with pytest.raises(ApiError) as refused:
            client.stop()
        assert refused.value.status == 409


@pytest.fixture
def canned() -> Iterator[tuple[str, list[bytes], list[bytes]]]:
    """A server of one connection on 127.0.0.1: it reads the request's head, sends what the
    test put in `answers` (None: nothing, and holds the connection open until the end)."""
    listener = socket.create_server(("127.0.0.1", 0))
    answers: list[bytes] = []
    seen: list[bytes] = []
    done = threading.Event()

    def serve() -> None:
        listener.settimeout(20)
        try:
            conn, _ = listener.accept()
        except OSError:
            return
        with conn:
            conn.settimeout(20)
            head = b""
            while b"\r\n\r\n" not in head and (part := conn.recv(4096)):
                head += part
            seen.append(head)
            if answers:
                conn.sendall(answers[0])
            else:
                done.wait(20)

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{listener.getsockname()[1]}", answers, seen
    done.set()
    listener.close()
    thread.join(25)


def test_a_chunked_answer(canned: tuple[str, list[bytes], list[bytes]]) -> None:
    url, answers, seen = canned
    answers.append(b"HTTP/1.1 100 Continue\r\n\r\nHTTP/1.1 200 OK\r\n"
                   b"Transfer-Encoding: chunked\r\nContent-Type: application/json\r\n\r\n"
                   b"7;ext=1\r\n{\"state\r\n9\r\n\": \"RUN\"}\r\n0\r\nX-Trailer: 1\r\n\r\n")
    assert ApiClient(url, token="k").status() == {"state": "RUN"}
    request = seen[0].decode()
    assert request.startswith("GET /api/v1/status HTTP/1.1\r\n")
    assert f"Host: {url[7:]}\r\n" in request and "Connection: close\r\n" in request
    assert "Authorization: Bearer k\r\n" in request


def test_an_answer_to_the_close_and_an_error_status(
        canned: tuple[str, list[bytes], list[bytes]]) -> None:
    url, answers, _ = canned
    answers.append(b"HTTP/1.1 409 Conflict\r\n\r\n{\"error\": \"not now\"}")
    with pytest.raises(ApiError) as refused:
        ApiClient(url, token="k").stop()
    assert refused.value.status == 409 and refused.value.message == "not now"


@pytest.mark.parametrize(("sent", "said"), [
    (b"", "cannot reach the softplc API at URL: Remote end closed connection without response"),
    (b"SSH-2.0-OpenSSH\r\n", "cannot reach the softplc API at URL: not an HTTP answer"),
    (b"HTTP/1.1 200 OK\r\nContent-Length: 50\r\n\r\n{}", "the answer from URL broke off: "
     "the body ended after 2 of 50 bytes"),
    (b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n", "broke off: bad chunk"),
    (b"HTTP/1.1 200 OK\r\nContent-Le", "cannot reach the softplc API at URL: the answer broke"),
])
def test_a_broken_answer_is_unreachable(canned: tuple[str, list[bytes], list[bytes]],
                                        sent: bytes, said: str) -> None:
    url, answers, _ = canned
    answers.append(sent)
    with pytest.raises(ApiUnreachable) as failed:
        ApiClient(url, token="k", timeout_s=10).status()
    assert said.replace("URL", url) in str(failed.value), failed.value


def test_silence_times_out(canned: tuple[str, list[bytes], list[bytes]]) -> None:
    url, _, _ = canned  # no answer: the server holds the connection open
    with pytest.raises(ApiUnreachable, match=f"cannot reach the softplc API at {url}: timed out"):
        ApiClient(url, token="k", timeout_s=0.3).status()
