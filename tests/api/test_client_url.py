"""The client commands' API URL (issue 40, item 4): $SOFTPLC_API when --api is not given,
--api when it is, http://127.0.0.1:8080 without either. Against closed ports: the command
says which URL it could not reach (a served one: tests/runtime/test_run_endpoints.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from softplc.api.client import DEFAULT_URL, URL_ENV, default_url
from tests.support import free_port

ROOT = Path(__file__).resolve().parents[2]


def unreachable(*argv: str, env: dict[str, str]) -> str:
    """What `softplc ARGV` says on stderr, nothing answering at its URL (exit code 2)."""
    done = subprocess.run([sys.executable, "-m", "softplc.cli", *argv, "--timeout", "5"],
                          capture_output=True, text=True, timeout=60,
                          env={**{k: v for k, v in os.environ.items() if k != URL_ENV},
                               "PYTHONPATH": str(ROOT), **env})
    assert done.returncode == 2, done.stderr
    return done.stderr


def test_a_client_command_takes_its_url_from_the_environment() -> None:
    url = f"http://127.0.0.1:{free_port()}"
    assert f"API at {url}:" in unreachable("status", env={URL_ENV: url})
    assert f"API at {url}:" in unreachable("stop", env={URL_ENV: url})


def test_an_explicit_api_wins_over_the_environment() -> None:
    port = free_port()
    given, env = f"http://127.0.0.1:{port}", f"http://127.0.0.3:{port}"
    said = unreachable("status", "--api", given, env={URL_ENV: env})
    assert f"API at {given}:" in said and env not in said


def test_without_either_the_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(URL_ENV, raising=False)
    assert default_url() == DEFAULT_URL
    monkeypatch.setenv(URL_ENV, "")
    assert default_url() == DEFAULT_URL  # set but empty: as if unset
