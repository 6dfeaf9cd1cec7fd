"""ApiClient, the CLI handlers and the remote-softplc driver against the live service."""

from __future__ import annotations

import argparse
import json
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api.clicmds import (
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_UNREACHABLE,
    format_status,
)
from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.cli import build_parser
from softplc.core.lifecycle import PlcState
from softplc.devices.driver import DeviceUnavailable, ProgramHandlingError
from softplc.interface.remote import RemoteProgramRefused, RemoteSoftplc
from softplc.security import auth
from tests.api.conftest import Plc, ScanThread, ServerThread, make_server
from tests.api.helpers import BAD_PROGRAM, TRANSPORT
from tests.support import eventually


@pytest.fixture
def dead_url() -> str:
    """A loopback port where nothing listens."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    return f"http://127.0.0.1:{port}"


@pytest.fixture(autouse=True)
def _no_env_token(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(auth.TOKEN_ENV, raising=False)


# -- ApiClient ----------------------------------------------------------------------------


def test_client_program_handling_and_status(api: ServerThread, tmp_path: Path) -> None:
    client = ApiClient(api.url)
    assert client.download(TRANSPORT)["state"] == "STOPPED"
    assert client.download(str(TRANSPORT))["state"] == "STOPPED"
    assert client.start()["state"] == "RUNNING"
    assert client.download(TRANSPORT.read_text(), online=True)["state"] == "RUNNING"
    assert client.stop()["state"] == "STOPPED"
    assert client.resume()["state"] == "RUNNING"
    assert client.kill()["state"] == "KILLED"
    assert client.reset()["state"] == "STOPPED"
    status = eventually(lambda: (s := client.status())["program"] and s)
    assert status["program"] == "transport"


def test_client_symbols(api: ServerThread) -> None:
    client = ApiClient(api.url)
    client.download(TRANSPORT)
    eventually(lambda: client.symbols())
    assert client.read_symbol("hold") is False
    assert client.write_symbol("hold", True)["queued"] is True
    eventually(lambda: client.read_symbol("hold") is True)
    with pytest.raises(ApiError) as refused:
        client.write_symbol("s1_i", 1)
    assert refused.value.status == 403
    with pytest.raises(ApiError) as unknown:
        client.read_symbol("no/such symbol")
    assert unknown.value.status == 404


def test_client_errors_carry_every_problem(api: ServerThread) -> None:
    client = ApiClient(api.url)
    with pytest.raises(ApiError) as bad:
        client.download(BAD_PROGRAM, name="my broken.yaml")
    assert bad.value.status == 422
    assert len(bad.value.problems) >= 4
    assert all("my_broken.yaml:" in p for p in bad.value.problems)
    with pytest.raises(ApiError) as refused:
        client.stop()
    assert refused.value.status == 409 and "EMPTY" in refused.value.message


def test_client_openapi(api: ServerThread) -> None:
    assert "/api/v1/program" in ApiClient(api.url).openapi()["paths"]


def test_client_cannot_connect(dead_url: str) -> None:
    with pytest.raises(ApiUnreachable, match="cannot reach the softplc API") as failed:
        ApiClient(dead_url, timeout_s=2).status()
    assert isinstance(failed.value, ConnectionError)
    with pytest.raises(ValueError, match="API URL"):
        ApiClient("ftp://127.0.0.1:1")


def test_client_token_from_argument_env_or_state_dir(plc_parts: Plc, scan: ScanThread,
                                                      tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    state = tmp_path / "state"
    with make_server(plc_parts, state, token_required=True) as api:
        token = (state / auth.TOKEN_FILE).read_text().strip()
        with pytest.raises(ApiError) as denied:
            ApiClient(api.url, local=False).status()
        assert denied.value.status == 401 and token not in str(denied.value)
        assert "--token" in denied.value.message
        # The account running the server finds its key by the URL (the local index).
        assert ApiClient(api.url).whoami() == {"user": "owner", "role": "admin", "via": "owner"}
        assert ApiClient(api.url, token=token).status()["state"]
        assert ApiClient(api.url, state_dir=state).status()["state"]
        monkeypatch.setenv(auth.TOKEN_ENV, token)
        assert ApiClient(api.url, local=False).status()["state"]
        assert token not in repr(ApiClient(api.url))


# -- CLI ----------------------------------------------------------------------------------


def run_cli(*argv: str) -> int:
    args = build_parser().parse_args(argv)
    code: int = args.func(args)
    return code


def test_cli_download_start_status(api: ServerThread, capsys: pytest.CaptureFixture[str]
                                   ) -> None:
    assert run_cli("download", str(TRANSPORT), "--api", api.url) == EXIT_OK
    assert "STOPPED" in capsys.readouterr().out
    assert run_cli("start", "--api", api.url) == EXIT_OK
    assert "RUNNING" in capsys.readouterr().out
    assert run_cli("download", str(TRANSPORT), "--online", "--api", api.url) == EXIT_OK
    capsys.readouterr()

    def running_status() -> dict[str, object] | None:
        assert run_cli("status", "--json", "--api", api.url) == EXIT_OK
        status: dict[str, object] = json.loads(capsys.readouterr().out)
        return status if status["state"] == "RUNNING" else None

    status = eventually(running_status)
    for key in ("state", "program", "program_hash", "scan_count", "marking", "timing",
                "start_mode"):
        assert key in status
    timing = status["timing"]
    assert isinstance(timing, dict) and {"p99_lateness_us", "overruns"} <= timing.keys()

    assert run_cli("status", "--api", api.url) == EXIT_OK
    text = capsys.readouterr().out
    assert "transport" in text and "RUNNING" in text and "overruns" in text
    for command in ("stop", "resume", "kill", "reset"):
        assert run_cli(command, "--api", api.url) == EXIT_OK, command
    capsys.readouterr()


def test_cli_bad_program_prints_every_problem(api: ServerThread, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "broken.yaml"
    bad.write_text(BAD_PROGRAM)
    assert run_cli("download", str(bad), "--api", api.url) == EXIT_REFUSED
    err = capsys.readouterr().err
    problem_lines = [line for line in err.splitlines() if "broken.yaml:" in line]
    assert len(problem_lines) >= 4
    assert "problem(s)" in err
    missing = tmp_path / "missing.yaml"
    assert run_cli("download", str(missing), "--api", api.url) == EXIT_REFUSED
    assert "cannot read" in capsys.readouterr().err


def test_cli_refused_command(api: ServerThread, capsys: pytest.CaptureFixture[str]) -> None:
    assert run_cli("start", "--api", api.url) == EXIT_REFUSED
    err = capsys.readouterr().err
    assert "409" in err and "EMPTY" in err and "start" in err


def test_cli_cannot_connect(dead_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    for argv in (("status",), ("start",), ("download", str(TRANSPORT)), ("status", "--json")):
        assert run_cli(*argv, "--api", dead_url, "--timeout", "2") == EXIT_UNREACHABLE
        assert "cannot reach" in capsys.readouterr().err
    assert run_cli("status", "--api", "nonsense") == EXIT_UNREACHABLE


def test_cli_token_options(plc_parts: Plc, scan: ScanThread, tmp_path: Path,
                           capsys: pytest.CaptureFixture[str],
                           monkeypatch: pytest.MonkeyPatch) -> None:
    state = tmp_path / "state"
    with make_server(plc_parts, state, token_required=True) as api:
        token = (state / auth.TOKEN_FILE).read_text().strip()
        assert run_cli("status", "--api", api.url) == EXIT_OK  # the owner's key, found
        monkeypatch.setenv(auth.INDEX_ENV, str(tmp_path / "elsewhere"))  # not found
        assert run_cli("status", "--api", api.url) == EXIT_REFUSED
        assert "401" in capsys.readouterr().err
        assert run_cli("status", "--api", api.url, f"--token={token}") == EXIT_OK
        assert run_cli("status", "--api", api.url, "--state-dir", str(state)) == EXIT_OK
        assert token not in capsys.readouterr().out


def test_cli_default_api_url_is_documented() -> None:
    parser = build_parser()
    (sub,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    help_text = sub.choices["status"].format_help()
    assert "http://127.0.0.1:8080" in help_text
    assert parser.parse_args(["kill"]).api == "http://127.0.0.1:8080"


def test_format_status_of_a_sparse_document() -> None:
    text = format_status({"state": "EMPTY"})
    assert "EMPTY" in text and "(none)" in text


# -- remote softplc -----------------------------------------------------------------------


@pytest.fixture
def remote(api: ServerThread) -> Iterator[RemoteSoftplc]:
    yield RemoteSoftplc(api.url, timeout_s=5)


def test_remote_facade_return_codes(remote: RemoteSoftplc, tmp_path: Path) -> None:
    assert remote.start() == -1 and "EMPTY" in remote.last_error
    assert remote.download(TRANSPORT.name, str(TRANSPORT.parent)) == 0
    assert remote.last_error == ""
    assert remote.start("transport") == 0
    assert remote.start() == -1 and "RUNNING" in remote.last_error
    assert remote.stop("transport.yaml") == 0
    assert remote.resume() == 0
    assert remote.kill() == 0
    assert remote.reset() == 0
    assert remote.start("another_program") == -1
    assert "another_program" in remote.last_error
    bad = tmp_path / "broken.yaml"
    bad.write_text(BAD_PROGRAM)
    assert remote.download(str(bad)) == -1 and "broken.yaml:4:" in remote.last_error
    assert remote.download(str(tmp_path / "missing.yaml")) == -1


def test_remote_python_style(remote: RemoteSoftplc, tmp_path: Path) -> None:
    assert "download" in remote.download_program(TRANSPORT)
    assert remote.start_program() is PlcState.RUNNING
    assert remote.state() is PlcState.RUNNING
    with pytest.raises(ProgramHandlingError, match="RUNNING"):
        remote.resume_program()
    bad = tmp_path / "broken.yaml"
    bad.write_text(BAD_PROGRAM)
    with pytest.raises(RemoteProgramRefused) as refused:
        remote.download_program(bad, online=True)
    assert refused.value.status == 422 and len(refused.value.problems) >= 4
    assert remote.stop_program() is PlcState.STOPPED
    assert remote.kill_program() is PlcState.KILLED
    assert remote.reset_program() is PlcState.STOPPED


def test_remote_unreachable(dead_url: str) -> None:
    remote = RemoteSoftplc(dead_url, timeout_s=2)
    assert remote.start() == -1 and "cannot reach" in remote.last_error
    with pytest.raises(DeviceUnavailable):
        remote.stop_program()
    with pytest.raises(DeviceUnavailable):
        remote.download_program(TRANSPORT)
