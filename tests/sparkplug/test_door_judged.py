"""The Sparkplug door judges a host's command against the program that runs, and audits every
outcome, a failure of its own included (tests/security/test_doors.py names this door).

In this process: the door's worker thread, a real audit trail in a temporary state directory,
the running program's status board as a document; the PLC side of the channel records what
reached it.

- A command whose handling raises (the channel to the scan process broke under it) is a
  `failed` record and an answered outcome, and the door takes the next command (it was only
  logged: no record, no answer).
- After a download while the broker was away, an NCMD that arrives before the node's next
  NBIRTH names its metric in the previous NBIRTH: it is judged against the running program
  (a symbol the new program added is written at its address; one it declared
  `hmi_writable: false` is refused; an alias of the previous birth is refused), not against
  the old symbols (they said "no metric" or "the program changed" to every such write).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from softplc.core.image import ImageSizes, ProcessImage, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import CommandReply, CommandRequest, HmiWrite, Snapshot, Status
from softplc.security.audit import AuditTrail
from softplc.security.roles import Role
from softplc.sparkplug.codec import DOUBLE, Metric
from softplc.sparkplug.config import SparkplugConfig
from softplc.sparkplug.door import Door
from softplc.sparkplug.metrics import COMMAND, Report

BEFORE: Mapping[str, Any] = {"program_hash": "h1", "program": "p1", "symbols": {
    "fill_to": {"type": "real", "address": "%MD1", "direction": "memory"},
    "level": {"type": "real", "address": "%MD2", "direction": "memory"}}}
AFTER: Mapping[str, Any] = {"program_hash": "h2", "program": "p2", "symbols": {
    "drain": {"type": "int", "address": "%MW20", "direction": "memory"},
    "fill_to": {"type": "real", "address": "%MD1", "direction": "memory",
                "hmi_writable": False}}}


class _Plc:
    """The scan's side of the channel and its snapshot, running `program`."""

    def __init__(self, program: str, broken: int = 0) -> None:
        self.program = program
        self.writes: list[HmiWrite] = []
        self.broken = broken  # writes that find the channel broken

    def send_hmi_write(self, write: HmiWrite) -> None:
        if self.broken:
            self.broken -= 1
            raise BrokenPipeError("the scan process closed its end")
        self.writes.append(write)

    def send_command(self, request: CommandRequest, timeout_s: float = 5.0) -> CommandReply:
        return CommandReply(request.id, True, "ok", PlcState.RUNNING)

    def latest(self) -> Snapshot:
        return Snapshot(1, ProcessImage(ImageSizes()),
                        Status(PlcState.RUNNING, program_hash=self.program))


def _door(tmp_path: Path, plc: _Plc, board: Mapping[str, Any] | None = None) -> Door:
    config = SparkplugConfig("127.0.0.1", 1, "plant", "n1", role=Role.OPERATOR,
                             state_dir=str(tmp_path))
    if board is None:
        return Door(config, plc, plc, AuditTrail(tmp_path))
    return Door(config, plc, plc, AuditTrail(tmp_path), lambda: dict(board))


def _outcomes(door: Door, count: int) -> list[str]:
    lines: list[str] = []
    deadline = time.monotonic() + 10
    while len(lines) < count and time.monotonic() < deadline:
        lines += door.outcomes()
        time.sleep(0.01)
    return lines


def _trail(state: Path) -> list[dict[str, Any]]:
    path = state / "audit.jsonl"
    return [json.loads(x) for x in path.read_text().splitlines()] if path.exists() else []


def test_a_failure_in_the_door_is_audited_answered_and_survived(tmp_path: Path) -> None:
    plc = _Plc("h1", broken=1)
    door = _door(tmp_path, plc)
    try:
        door.submit(Report(BEFORE, 0.0), Metric("fill_to", DOUBLE, 1.5))
        door.submit(Report(BEFORE, 0.0), Metric("fill_to", DOUBLE, 2.5))
        lines = _outcomes(door, 2)
    finally:
        door.close()
    assert len(lines) == 2, lines
    assert lines[0].startswith("#1 write fill_to: failed (the door failed (BrokenPipeError")
    assert lines[1] == "#2 write fill_to: queued"
    records = _trail(tmp_path)
    assert [(r["iface"], r["outcome"]) for r in records] == [("sparkplug", "failed"),
                                                             ("sparkplug", "queued")]
    assert "BrokenPipeError" in records[0]["status"]
    assert [w.address for w in plc.writes] == [parse_address("%MD1")]


def test_commands_after_a_download_are_judged_against_the_running_program(
        tmp_path: Path) -> None:
    plc = _Plc("h2")  # downloaded while the broker was away; the node's birth is still h1's
    door = _door(tmp_path, plc, AFTER)
    old_birth = Report(BEFORE, 0.0)
    try:
        door.submit(old_birth, Metric("drain", None, 7))
        door.submit(old_birth, Metric("fill_to", DOUBLE, 2.5))
        door.submit(old_birth, Metric(None, None, 2.5, old_birth.by_name["level"].alias))
        door.submit(old_birth, Metric("level", DOUBLE, 1.0))
        door.submit(old_birth, Metric(None, None, "stop", old_birth.node_alias[COMMAND]))
        lines = _outcomes(door, 5)
    finally:
        door.close()
    assert lines == [
        "#1 write drain: queued",
        "#2 write fill_to: refused (symbol fill_to is declared hmi_writable: false)",
        f"#3 write alias {old_birth.by_name['level'].alias}: refused (the program changed "
        "since the last NBIRTH: its aliases name other metrics now; send the name, or the "
        "alias of the next NBIRTH)",
        "#4 write level: refused (no metric level in the running program)",
        # a node metric's alias is the same in every birth: still the command metric
        "#5 stop Node Control/Command: refused (program commands are off "
        "(--sparkplug-commands))"]
    assert plc.writes == [HmiWrite(parse_address("%MW20"), (7,))]
    assert [r["outcome"] for r in _trail(tmp_path)] == ["queued", "refused", "refused",
                                                        "refused", "refused"]


def test_without_a_change_the_last_birth_is_the_judge(tmp_path: Path) -> None:
    plc = _Plc("h1")
    door = _door(tmp_path, plc, AFTER)  # a board not read: the birth's program runs
    birth = Report(BEFORE, 0.0)
    try:
        door.submit(birth, Metric(None, None, 4.0, birth.by_name["level"].alias))
        lines = _outcomes(door, 1)
    finally:
        door.close()
    assert lines == ["#1 write level: queued"]
    assert [w.address for w in plc.writes] == [parse_address("%MD2")]
