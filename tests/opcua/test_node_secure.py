"""node-opcua's client with SignAndEncrypt (Basic256Sha256) and a user name against a real
`softplc run` (issue 31): its own certificate is refused and kept in STATE_DIR/pki/rejected;
after `softplc trust accept` the channel opens, an operator's UserExecutable of Suspend is
true and Suspend and Resume are applied. Skips as test_node_opcua.py does without node."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.opcua.conftest import ROOT, Plc
from tests.opcua.test_node_opcua import NODE_DIR, node_modules

__all__ = ["node_modules"]  # the fixture, shared with test_node_opcua.py
SCRIPT_BOUND_S = 60.0  # the script bounds itself at 40 s
PASSWORD = "operator-password"


def _run(modules: Path, plc: Plc) -> dict[str, Any]:
    env = {"NODE_PATH": str(modules), "PATH": os.environ.get("PATH", "/usr/bin:/bin"),
           "HOME": str(plc.state_dir / "node-home")}  # node-opcua's PKI (its certificate)
    done = subprocess.run([shutil.which("node") or "node", str(NODE_DIR / "secure.js"),
                           plc.url, "op", PASSWORD], capture_output=True, text=True,
                          timeout=SCRIPT_BOUND_S, check=False, env=env, cwd=plc.state_dir)
    lines = done.stdout.strip().splitlines()
    assert lines, f"node wrote no report (exit {done.returncode}):\n{done.stderr[-3000:]}"
    report: dict[str, Any] = json.loads(lines[-1])
    print(done.stderr[-2000:], json.dumps(report))
    return report


def test_node_opcua_sign_and_encrypt(node_modules: Path, transport_plc: Plc) -> None:
    plc = transport_plc
    UserStore(plc.state_dir).add("op", Role.OPERATOR, PASSWORD)
    refused = _run(node_modules, plc)
    assert "session" not in refused and "error" in refused, refused
    kept = list((plc.state_dir / "pki" / "rejected").glob("*.der"))
    assert len(kept) == 1, kept
    accept = subprocess.run([sys.executable, "-m", "softplc.cli", "trust", "accept",
                             kept[0].stem, "--state-dir", str(plc.state_dir)], cwd=ROOT,
                            capture_output=True, text=True, timeout=60, check=False)
    assert accept.returncode == 0, accept.stderr
    report = _run(node_modules, plc)
    assert "error" not in report, report
    assert report["userExecutableSuspend"] is True
    assert (report["suspend"], report["resume"]) == ("Good", "Good")
