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
