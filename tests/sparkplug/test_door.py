"""The Sparkplug door's security: a broker with user/password over TLS (openssl-made CA, the
password from a file, not in the command line), the default role viewer (a write is denied,
answered in the status metric and audited; program commands are off), and a door configured
operator with --sparkplug-commands (stop applied, reset denied: it needs engineer)."""

from __future__ import annotations

import json
import os
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.sparkplug.conftest import Broker, Host, Tahu, metrics_of, start_plc, stop_plc
from tests.support import wait_until

TOPIC = "spBv1.0/plant/%s/tank1"

pytestmark = pytest.mark.slow  # real softplc runs against a real broker


def _ndata_strings(tahu: Tahu, host: Host, start: int, alias: int) -> list[str]:
    payloads = [m.payload for _, m in host.since(start, "NDATA")]
    return [m["stringValue"] for d in (tahu.decode(payloads) if payloads else [])
            for m in d["raw"].get("metrics", [])
            if int(m.get("alias", -1)) == alias and "stringValue" in m]


def _await_string(tahu: Tahu, host: Host, start: int, alias: int, want: str) -> None:
    seen: list[str] = []

    def found() -> bool:
        seen[:] = _ndata_strings(tahu, host, start, alias)
        return any(want in s for s in seen)

    assert wait_until(found, 30.0, 0.3), f"no {want!r} in NDATA; saw {seen}"


def _trail(state: Path) -> list[dict[str, Any]]:
    path = state / "audit.jsonl"
    return [json.loads(x) for x in path.read_text().splitlines() if '"sparkplug"' in x] \
        if path.exists() else []


def _sparkplug_pid(supervisor: int) -> int:
    """The supervisor's child named softplc-spb (Linux keeps 15 bytes of a name)."""
    found = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
             and _parent(p) == supervisor and _comm(p) == "softplc-spb"]
    assert len(found) == 1, found
    return found[0]


def _parent(proc: Path) -> int:
    try:
        return int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return -1


def _comm(proc: Path) -> str:
    try:
        return (proc / "comm").read_text().strip()
    except OSError:
        return ""


def _cmd(tahu: Tahu, name: str, type_name: str, value: object) -> bytes:
    return tahu.encode({"timestamp": 1, "metrics": [{"name": name, "type": type_name,
                                                     "value": value}]})


def test_tls_password_file_and_the_default_viewer_role(
        tmp_path: Path, tahu: Tahu, mosquitto: Callable[..., Broker],
        host: Callable[..., Host]) -> None:
    broker = mosquitto(users={"plc": "s3cret pass", "scada": "scada-pw"}, tls=True)
    ca = str(broker.dir / "ca.crt")
    h = host(broker.port, "scada", "scada-pw", ca)
    state = tmp_path / "state"
    state.mkdir()
    (state.parent / "pw").write_text("s3cret pass\n")
    plc = start_plc(state, f"mqtts://plc@127.0.0.1:{broker.port}/plant/tank1",
                    "--sparkplug-ca", ca, "--sparkplug-password-file", str(state.parent / "pw"))
    try:
        _, birth = h.wait("NBIRTH")
        status = int(metrics_of(tahu.decode([birth.payload])[0])
                     ["Node Control/Command Status"]["alias"])
        h.send(TOPIC % "NCMD", _cmd(tahu, "fill_to", "Float", 10.0))
        _await_string(tahu, h, 0, status, "write fill_to: denied (write needs operator")
        h.send(TOPIC % "NCMD", _cmd(tahu, "Node Control/Command", "String", "stop"))
        _await_string(tahu, h, 0, status, "program commands are off")
        assert wait_until(lambda: [r["outcome"] for r in _trail(state)] == ["denied",
                                                                            "refused"])
    finally:
        stop_plc(plc)
    assert "s3cret" not in (state / "run.log").read_text()
    assert "Will message specified" in broker.log_text()


def test_operator_with_commands_stops_but_may_not_reset(
        tmp_path: Path, tahu: Tahu, mosquitto: Callable[..., Broker],
        host: Callable[..., Host]) -> None:
    broker = mosquitto()
    h = host(broker.port)
    state = tmp_path / "state"
    plc = start_plc(state, f"mqtt://127.0.0.1:{broker.port}/plant/tank1",
                    "--sparkplug-role", "operator", "--sparkplug-commands")
    try:
        _, birth = h.wait("NBIRTH")
        metrics = metrics_of(tahu.decode([birth.payload])[0])
        state_alias = int(metrics["PLC/State"]["alias"])
        status = int(metrics["Node Control/Command Status"]["alias"])
        h.send(TOPIC % "NCMD", _cmd(tahu, "Node Control/Command", "String", "stop"))
        _await_string(tahu, h, 0, status, "stop Node Control/Command: applied")
        _await_string(tahu, h, 0, state_alias, "STOPPED")
        command = int(metrics["Node Control/Command"]["alias"])  # by alias, as Ignition does
        h.send(TOPIC % "NCMD", tahu.encode({"timestamp": 1, "metrics": [
            {"alias": command, "type": "String", "value": "reset"}]}))
        _await_string(tahu, h, 0, status, "reset Node Control/Command: denied (reset needs "
                      "engineer")
        assert wait_until(lambda: [(r["action"], r["outcome"]) for r in _trail(state)] == [
            ("stop", "applied"), ("reset", "denied")])
        # the Sparkplug process alone killed: the broker's Will, the supervisor restarts it
        # (a new CONNECT: the next bdSeq), the PLC went on
        pid = _sparkplug_pid(plc.pid)
        mark = h.count()
        os.kill(pid, signal.SIGKILL)
        _, death = h.wait("NDEATH", mark)
        assert int(tahu.decode([death.payload])[0]["payload"]["metrics"][0]["value"]) == 0
        _, reborn = h.wait("NBIRTH", mark)
        assert int(metrics_of(tahu.decode([reborn.payload])[0])["bdSeq"]["value"]) == 1
        assert _sparkplug_pid(plc.pid) != pid and plc.poll() is None
    finally:
        stop_plc(plc)
