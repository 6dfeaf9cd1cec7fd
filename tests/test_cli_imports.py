"""A client command starts without numpy, the compiler or the servers (issue 40): `softplc
status` is run in a fresh interpreter, which then names every module it imported."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("numpy", "softplc.program.compiler", "softplc.api.server", "softplc.api.tlsproto",
         "cryptography", "aiohttp", "asyncua", "pymodbus", "yaml")
# Runs the command as `softplc` does, then prints sys.modules whatever the exit code.
WRAPPER = """
import json, sys
from softplc.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print(json.dumps(sorted(sys.modules)), file=sys.stderr)
"""


def imported_by(*argv: str) -> tuple[int, set[str]]:
    done = subprocess.run([sys.executable, "-c", WRAPPER, *argv], cwd=ROOT, text=True,
                          capture_output=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    modules: list[str] = json.loads(done.stderr.splitlines()[-1])
    return done.returncode, set(modules)


def free_port() -> int:
    """A loopback port nobody listens on: the command must fail to connect, not hang."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.mark.parametrize("argv", [
    ("status", "--help"),
    ("status", "--json", "--api", "URL"),
    ("stop", "--api", "URL"),
    ("force", "hold", "1", "--api", "URL"),
    ("step", "--api", "URL"),
    ("why", "start", "--json", "--api", "URL"),
    ("--help",),
])
def test_a_client_command_imports_no_numpy_compiler_or_server(argv: tuple[str, ...]) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    code, modules = imported_by(*(url if arg == "URL" else arg for arg in argv))
    assert code in (0, 2), code  # 2: no API answering at the free port
    heavy = sorted(m for m in modules if m.split(".")[0] in HEAVY or m in HEAVY)
    assert not heavy, f"softplc {' '.join(argv)} imported {heavy}"


def test_only_the_command_run_is_imported() -> None:
    _, modules = imported_by("status", "--help")
    others = {"softplc.analysis.cli", "softplc.debug.debugcli", "softplc.debug.breakcli",
              "softplc.api.admincmds", "softplc.api.signcmds", "softplc.api.trustcmds",
              "softplc.cli.local", "softplc.cli.runargs"}
    assert not modules & others, sorted(modules & others)


# Taken off the client path (issue 40 item 1), each a cost of every start: typing and
# dataclasses (with inspect, ast, dis) by cli/table.py, core/ and the client; difflib (only a
# mistyped command); the server's hmac and secrets (security/auth.py); the TLS settings and
# context modules (only for an https URL); urllib.request with http.client, email and ssl (an
# http URL goes over api/plainhttp.py's socket; against a served API: tests/api/test_plainhttp.py).
TRIMMED = ("typing", "dataclasses", "inspect", "difflib", "hmac", "secrets",
           "softplc.security.tls", "softplc.security.settings", "softplc.api.secopts",
           "urllib.request", "http.client", "email", "ssl")


@pytest.mark.parametrize("argv", [("status", "--json", "--api", "URL"), ("--help",),
                                  ("--version",)])
def test_the_client_path_stays_trimmed(argv: tuple[str, ...]) -> None:
    url = f"http://127.0.0.1:{free_port()}"
    code, modules = imported_by(*(url if arg == "URL" else arg for arg in argv))
    assert code in (0, 2), code
    back = sorted(modules & set(TRIMMED))
    assert not back, f"softplc {' '.join(argv)} imported {back}"


@pytest.mark.parametrize("argv", [("--help",), ("--version",)])
def test_help_and_version_import_no_http_client(argv: tuple[str, ...]) -> None:
    code, modules = imported_by(*argv)
    assert code == 0
    client = sorted(modules & {"softplc.api.client", "urllib.request", "http.client", "ssl",
                               "email", "pathlib"})  # json: the wrapper imports it
    assert not client, client


def test_version_builds_no_parser() -> None:
    """`softplc --version` prints without the parser of 30 commands (argparse's help
    formatter imports shutil when it is made)."""
    code, modules = imported_by("--version")
    assert code == 0 and "shutil" not in modules


@pytest.mark.parametrize(("argv", "top"), [(["status", "extra"], True),
                                           (["status", "--jsn"], True),
                                           (["stop", "--api"], False), (["force"], False)])
def test_a_usage_error_after_a_command_is_worded_as_before(
        argv: list[str], top: bool, capsys: pytest.CaptureFixture[str]) -> None:
    """A command is parsed by a parser of that command alone; its usage errors are worded by
    the whole parser, as before: the top level's usage line names every command."""
    from softplc.cli import parse
    from softplc.cli.table import COMMANDS

    with pytest.raises(SystemExit) as stopped:
        parse(argv)
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert err.count("error:") == 1, err
    if top:  # unrecognized arguments: the top level's error
        assert "{" + ",".join(COMMANDS) + "}" in err, err
    else:
        assert err.startswith(f"usage: softplc {argv[0]} "), err
