"""Breakpoints in the scan loop on a virtual clock (docs/debug.md): the transport PLC of `make
run` pauses when `handed_over` fires, the status board says so while the loop goes on cycling
(no watchdog, no stall, devices still read), a step is one scan, continue runs on; and
`simulate --break` headless, from the CLI, stops at the same scan."""

from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from softplc.api.clicmds import format_status
from softplc.cli import main
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = str(ROOT / "programs" / "transport.yaml")
MS = 1_000_000


class Board:
    """A status board that keeps what the loop publishes."""

    def __init__(self) -> None:
        self.docs: list[dict[str, Any]] = []

    def publish(self, document: dict[str, Any]) -> None:
        self.docs.append(document)


class Script:
    """The loop's stop flag, asked once per cycle: runs `plan[cycle](loop)`, stops at `end`."""

    def __init__(self, loop: ScanLoop, plan: dict[int, Callable[[ScanLoop], object]],
                 end: int) -> None:
        self.loop, self.plan, self.end, self.cycle = loop, plan, end, 0

    def is_set(self) -> bool:
        self.cycle += 1
        if (action := self.plan.get(self.cycle)) is not None:
            action(self.loop)
        return self.cycle > self.end

    def set(self) -> None:
        self.cycle = self.end

    def wait(self, timeout: float | None = None) -> bool:
        return self.is_set()


def command(cmd: Command, **kw: Any) -> Callable[[ScanLoop], object]:
    return lambda loop: loop.pending.append(ProgramCommand(cmd, **kw))


def transport_loop() -> tuple[ScanLoop, Board]:
    board = Board()
    config = LoopConfig(program=TRANSPORT, start=True, period_ns=10 * MS, plant="transport")
    loop = ScanLoop(config, None, None, VirtualClock(0), board=board)  # type: ignore[arg-type]
    return loop, board


def test_the_transport_plc_pauses_when_handed_over_fires_and_steps_one_scan() -> None:
    loop, board = transport_loop()
    seen: dict[str, Any] = {}

    def at_pause(loop: ScanLoop) -> None:
        seen["count"] = loop.runner.plc.scan_count
        seen["doc"] = loop.document()
        seen["outputs"] = loop.runner.plc.image.outputs_bytes()

    plan = {1: command(Command.BREAK, symbol="fire:handed_over"), 1000: at_pause,
            1001: command(Command.STEP), 1003: lambda loop: seen.update(
                stepped=loop.runner.plc.scan_count),
            1010: command(Command.CONTINUE)}
    loop.run(Script(loop, plan, 1100))  # type: ignore[arg-type]
    doc = seen["doc"]
    assert doc["state"] == "RUNNING" and doc["paused"]["reason"] == "b1: handed_over fires"
    assert format_status(doc).splitlines()[0] == (  # `softplc status`, read by a person
        f"state       RUNNING PAUSED after scan {seen['count'] - 1} (b1: handed_over fires; "
        "outputs hold; softplc step / continue)")
    assert doc["paused"]["scan_count"] == seen["count"] < 1000  # paused well before cycle 1000
    assert doc["paused"]["outputs"] == "hold"
    assert doc["breakpoints"][0]["target"] == "handed_over"
    assert seen["stepped"] == seen["count"] + 1  # exactly one scan
    plc = loop.runner.plc
    assert plc.state is PlcState.RUNNING and plc.fault_code == 0
    assert plc.scan_count == seen["count"] + 1 + (1100 - 1010 + 1)  # continue: every cycle
    assert loop.stats.overruns == 0 and loop.stalls == 0
    assert any(e["name"] == "paused:b1" for e in loop.events)
    # the board went on being published while paused, showing the pause
    paused_docs = [d for d in board.docs if d.get("paused")]
    assert len(paused_docs) >= 10


def test_safe_outputs_go_out_while_paused_and_come_back() -> None:
    loop, _ = transport_loop()
    seen: dict[str, Any] = {}

    def at_pause(loop: ScanLoop) -> None:
        plc = loop.runner.plc
        seen["paused"] = plc.image.qx.copy()
        seen["held"] = plc.debug.held.areas["qx"].copy() if plc.debug.held else None

    plan = {1: command(Command.BREAK, symbol="fire:hand_over", value=1), 900: at_pause,
            901: command(Command.CONTINUE),
            902: lambda loop: seen.update(after=loop.runner.plc.image.qx.copy())}
    loop.run(Script(loop, plan, 903))  # type: ignore[arg-type]
    plc = loop.runner.plc
    plc.drive_safe()
    assert (seen["paused"] == plc.image.qx).all()  # every output at its safe value (m1 off)
    assert seen["held"] is not None and (seen["held"] != seen["paused"]).any()
    assert (seen["after"] == seen["held"]).all()  # the program's own back once it runs on


def cli(*args: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return code, out.getvalue(), err.getvalue()


def test_simulate_break_stops_at_the_scan_and_steps_headless() -> None:
    code, out, err = cli("simulate", TRANSPORT, "--duration", "60s", "--break",
                         "transition:handed_over", "--json")
    assert code == 0, err
    report = json.loads(out)
    paused = report["paused"]
    assert paused["reason"] == "b1: handed_over fires" and report["scans"] == paused["k"] + 1
    assert report["fired"]["handed_over"] == 1 and report["state"] == "RUNNING"
    code, out, err = cli("simulate", TRANSPORT, "--duration", "60s", "--break",
                         "transition:handed_over", "--step", "3")
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0] == (f"paused after scan {paused['k']} (t={paused['t_s']:.3f} s, scan count "
                        f"{paused['k'] + 1}): b1: handed_over fires")
    assert lines[1].startswith(f"paused after scan {paused['k'] + 3} ")
    assert lines[1].endswith("step of 3 scan(s) done")
    code, out, err = cli("simulate", TRANSPORT, "--break", "transition:nothing")
    assert code == 1 and "no transition 'nothing' in program transport" in err
