"""The transport PLC as `make run` starts it, for the debugger's tests against a real process.

Owns: `transport_plc` (a `softplc run programs/transport.yaml --plant transport --start` on
free loopback ports, ready once it has scanned, ended at the end), `running` and `status`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import pytest

from softplc.api.client import ApiClient, ApiError
from tests.support import free_port, softplc_run


@contextlib.contextmanager
def transport_plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """(API URL, state directory) of a running transport PLC."""
    state = tmp_path_factory.mktemp("state")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run(["programs/transport.yaml", "--plant", "transport", "--start", "--api",
                      f"127.0.0.1:{port}", "--modbus", f"127.0.0.1:{free_port()}", "--opcua",
                      "off", "--state-dir", str(state), "--quiet"], lambda: running(url)):
        yield url, str(state)


def running(url: str) -> bool:
    try:
        return ApiClient(url, timeout_s=2).status().get("board_scan_count", 0) > 0
    except (ApiError, OSError):
        return False


def status(url: str) -> dict[str, Any]:
    return ApiClient(url, timeout_s=5).status()
