"""node-opcua (an OPC UA stack nobody here wrote; pinned in tests/opcua/node/package.json)
against a real `softplc run` (issue 29, item 5): browse, read with timestamps, writes,
a subscription with events on the Server object, the Part 10 methods in each state, and a
kill -9 of the OPC UA process after which the subscription delivers again within
RECOVERY_BOUND_S. node-opcua is installed once from the npm registry into .venv/node-opcua;
the test skips, saying why, when node or npm is missing (.ci/run installs them)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.opcua.conftest import ROOT, Plc, start_plc, stop_plc
from tests.opcua.pids import listener_pid
from tests.support import npm_modules

NODE_DIR = Path(__file__).resolve().parent / "node"
CACHE = ROOT / ".venv" / "node-opcua"
SCRIPT_BOUND_S = 70.0  # the script bounds itself at 55 s
RECOVERY_BOUND_S = 15.0  # kill -9 to the first data change of the re-created subscription
TRANSITION_EVENT = "ns=0;i=2378"  # ProgramTransitionEventType


@pytest.fixture(scope="session")
def node_modules() -> Path:
    """node-opcua's client at the pinned version, installed once (re-installed when
    package.json changes)."""
    return npm_modules(NODE_DIR, CACHE, "node-opcua")


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[Plc]:
    plc = start_plc("programs/transport.yaml", tmp_path)
    try:
        yield plc
    finally:
        stop_plc(plc.proc)


def _run_script(node_modules: Path, plc: Plc) -> dict[str, Any]:
    pid = listener_pid(plc.port)
    node = shutil.which("node") or "node"
    # HOME in the test's directory: whatever node-opcua keeps (a PKI folder) stays there.
    env = {"NODE_PATH": str(node_modules), "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
           "HOME": str(plc.state_dir)}
    done = subprocess.run([node, str(NODE_DIR / "interop.js"), plc.url, plc.token, str(pid)],
                          capture_output=True, text=True, timeout=SCRIPT_BOUND_S, check=False,
                          env=env, cwd=plc.state_dir)
    lines = done.stdout.strip().splitlines()
    assert lines, f"node wrote no report (exit {done.returncode}):\n{done.stderr[-3000:]}"
    report: dict[str, Any] = json.loads(lines[-1])
    assert "error" not in report, f"{report['error']}\n{done.stderr[-3000:]}"
    print(done.stderr[-3000:], json.dumps(report))  # shown with -s or on failure
    return report


def test_node_opcua_client(node_modules: Path, plc: Plc) -> None:
    report = _run_script(node_modules, plc)
    assert {"s1_i", "hold", "parts_delivered"} <= set(report["symbols"])
    read = report["read"]
    assert read["status"] == "Good" and read["source"] and read["server"]
    assert read["source"] <= read["server"] + 50 and read["now"] - read["source"] < 5000
    write_bit = 2
    access = report["access"]
    assert not access["anonymousUserAccessLevel"] & write_bit
    assert access["operatorUserAccessLevel"] & write_bit
    assert access["anonymousUserExecutableSuspend"] is False
    assert access["operatorUserExecutableSuspend"] is True  # Running: Suspend works
    assert report["writes"] == {"anonymous": "BadUserAccessDenied", "boolean": "Good",
                                "uint16ToBoolean": "BadTypeMismatch",
                                "int32ToUInt16": "BadTypeMismatch",
                                "unknown": "BadNodeIdUnknown", "holdReadBack": True}
    calls = [(c["method"], c["status"], c["after"]) for c in report["calls"]]
    assert calls == [
        ("Start", "BadInvalidState", "Running"), ("Reset", "BadInvalidState", "Running"),
        ("Resume", "BadInvalidState", "Running"), ("Suspend", "Good", "Suspended"),
        ("Start", "BadInvalidState", "Suspended"), ("Suspend", "BadInvalidState", "Suspended"),
        ("Resume", "Good", "Running"), ("Halt", "Good", "Halted"),
        ("Start", "BadInvalidState", "Halted"), ("Reset", "Good", "Ready"),
        ("Resume", "BadInvalidState", "Ready"), ("Halt", "Good", "Halted"),
        ("Reset", "Good", "Ready"), ("Start", "Good", "Running")]
    transitions = [e for e in report["events"] if e["type"] == TRANSITION_EVENT]
    goods = sum(status == "Good" for _, status, _ in calls)
    assert len(transitions) == goods, report["events"]  # one per Good call, on the Server
    recovery = report["recovery"]
    assert recovery["status"] == "Good" and recovery["seconds"] < RECOVERY_BOUND_S
    assert report["seconds"] < 60
