"""The cell case study (issue 14) as three real `softplc run` processes on loopback: the
transport and drilling PLCs on their simulated plants, loaded but not started, and the cell
controller (programs/cell.yaml) that starts them over OPC UA and orchestrates them.

Owns: free ports, the state dirs with their API tokens (made before the PLCs start, so the
cell gets them in its environment), the cell's io image rewritten to those ports, the
processes, and a watcher that reads the three PLCs over OPC UA and prints a timeline in the
style of `softplc simulate --timeline`.
Does not know: the nets (they are files), the scan, the plants' physics.

    python -m softplc.opcua.cell --parts 2   # 2 parts delivered, then drain: all drilled
"""

from __future__ import annotations

import argparse
import asyncio
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Final

from asyncua import Node, ua

from softplc.opcua.client import RefusingAwareClient
from softplc.opcua.ids import string_id
from softplc.security.auth import load_or_create_token

ROOT: Final = Path(__file__).resolve().parents[2]
PROGRAMS: Final = {"transport": "programs/transport.yaml", "drilling": "programs/drilling.yaml"}
DEFAULT_URLS: Final = {"transport": "opc.tcp://127.0.0.1:4841",
                       "drilling": "opc.tcp://127.0.0.1:4842"}
# What the watcher reads: (PLC, symbol) -> label in the timeline.
WATCHED: Final = (("transport", "parts_delivered"), ("drilling", "parts_drilled"),
                  ("drilling", "m_fwd"), ("cell", "parts_delivered"),
                  ("cell", "parts_released"), ("cell", "parts_drilled"))
STATES: Final = ("transport", "drilling", "cell")
# The transport's belts are empty (nothing on them but parts not yet taken on at s1_i) when
# these are all 0: a part on a belt either moves (m1/m2) or waits at a sensor.
BELTS: Final = ("m1", "m2", "s1_o", "s2_i", "s2_o")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True, slots=True)
class Sample:
    """One reading of the three PLCs, `t_s` seconds after the cell started."""

    t_s: float
    values: dict[tuple[str, str], int]
    states: dict[str, str]
    belts_empty: bool

    def drained(self) -> bool:
        """Every part the transport took on was delivered, and every one of them drilled."""
        v = self.values
        running = all(state == "RUNNING" for state in self.states.values())
        return running and self.belts_empty and (v[("drilling", "parts_drilled")]
                                     == v[("transport", "parts_delivered")]
                                     == v[("cell", "parts_drilled")])


@dataclass(slots=True)
class CellReport:
    """What the watcher saw: when each part was delivered and drilled, and every breach of
    the cell's promise (a part drilled that was never delivered)."""

    delivered_at: list[float] = field(default_factory=list)
    drilled_at: list[float] = field(default_factory=list)
    breaches: list[str] = field(default_factory=list)
    last: Sample | None = None
    faults: list[str] = field(default_factory=list)
    feed_ended: bool = False
    drained: bool = False

    def worst_lag_s(self) -> float:
        """Longest time from a part's delivery to its drilling (parts drilled so far)."""
        lags = [d - t for t, d in zip(self.delivered_at, self.drilled_at, strict=False)]
        return max(lags, default=0.0)


class CellRun:
    """Three `softplc run` processes in `work_dir` (a context manager; closes them all)."""

    def __init__(self, work_dir: Path, period: str = "10ms", cell_period: str = "50ms",
                 start_remotes: bool = False) -> None:
        self.work_dir = work_dir
        # The cell is the upper control level: 50 ms is plenty, and its scan process also
        # hosts two OPC UA clients (the drivers' I/O threads) that compete for the GIL.
        self.periods = {"transport": period, "drilling": period, "cell": cell_period}
        # start_remotes: start transport/drilling themselves (--start), so the cell's Start
        # calls are refused: the failure path of the case study.
        self.start_remotes = start_remotes
        self.ports = {name: free_port() for name in STATES}
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def url(self, name: str) -> str:
        return f"opc.tcp://127.0.0.1:{self.ports[name]}"

    def __enter__(self) -> CellRun:
        try:
            tokens = {name: load_or_create_token(self.state_dir(name)) for name in PROGRAMS}
            # One after the other: three processes importing asyncua at once on a busy machine
            # can miss the supervisor's start-up bound of the communication process.
            for name, program in PROGRAMS.items():
                self._launch(name, str(ROOT / program), self.start_remotes, {})
                self._wait_port(name, 90.0)
            env = {"TRANSPORT_TOKEN": tokens["transport"], "DRILLING_TOKEN": tokens["drilling"]}
            self._launch("cell", str(self._write_cell()), True, env)
            self._wait_port("cell", 90.0)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def state_dir(self, name: str) -> Path:
        return self.work_dir / name

    def log_tail(self, name: str, lines: int = 30) -> str:
        path = self.state_dir(name) / "run.log"
        text = path.read_text(errors="replace") if path.exists() else ""
        return "\n".join(text.splitlines()[-lines:])

    def _write_cell(self) -> Path:
        """programs/cell.yaml and its io image, the two remote URLs set to this run's ports."""
        (self.work_dir / "programs").mkdir(parents=True, exist_ok=True)
        (self.work_dir / "io_images").mkdir(parents=True, exist_ok=True)
        io_text = (ROOT / "io_images/cell.yaml").read_text()
        for name, default in DEFAULT_URLS.items():
            if default not in io_text:
                raise ValueError(f"io_images/cell.yaml: expected the url {default} of {name}")
            io_text = io_text.replace(default, self.url(name))
        (self.work_dir / "io_images/cell.yaml").write_text(io_text)
        program = self.work_dir / "programs/cell.yaml"
        program.write_text((ROOT / "programs/cell.yaml").read_text())
        return program

    def _launch(self, name: str, program: str, start: bool, env: dict[str, str]) -> None:
        state = self.state_dir(name)
        state.mkdir(parents=True, exist_ok=True)
        args = [sys.executable, "-m", "softplc.cli", "run", program, "--modbus", "off",
                "--api", "off", "--opcua", f"127.0.0.1:{self.ports[name]}",
                "--state-dir", str(state), "--quiet", "--period", self.periods[name],
                # A late cycle or a long scan on a busy machine (CI, shared cores) is not what
                # the case study is about: stalls are counted, the watchdog is 1 s at 10 ms.
                # Both policies have their own tests (docs/faults.md).
                "--on-stall", "continue", "--watchdog", "100"]
        if start:
            args.append("--start")
        # Output goes to a file: a pipe nobody reads fills up and blocks the writer.
        with (state / "run.log").open("wb") as log:
            self.procs[name] = subprocess.Popen(args, cwd=ROOT, stdout=log,
                                                stderr=subprocess.STDOUT,
                                                env={**os.environ, **env})

    def _wait_port(self, name: str, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.procs[name].poll() is not None:
                raise RuntimeError(f"{name} PLC exited:\n{self.log_tail(name)}")
            with socket.socket() as s:
                if s.connect_ex(("127.0.0.1", self.ports[name])) == 0:
                    return
            time.sleep(0.2)
        raise RuntimeError(f"{name} PLC: nothing listens on port {self.ports[name]}")

    def close(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.terminate()
        for proc in self.procs.values():
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


class Watcher:
    """Anonymous OPC UA reads (allowed on loopback) of the three PLCs."""

    def __init__(self, run: CellRun) -> None:
        self.run = run
        self.clients = {name: RefusingAwareClient(run.url(name), timeout=5, watchdog_intervall=5)
                        for name in STATES}
        # The cell's HMI bit end_feed is written, which needs a user token.
        self.clients["cell"].set_user("watcher")
        self.clients["cell"].set_password(load_or_create_token(run.state_dir("cell")))
        self.began = time.monotonic()

    async def __aenter__(self) -> Watcher:
        for client in self.clients.values():
            await client.connect()
        ns = {name: await c.get_namespace_index("urn:softplc") for name, c in self.clients.items()}

        def node(plc: str, path: str) -> Node:
            return self.clients[plc].get_node(string_id(path, ns[plc]))

        self._values = [(key, node(key[0], f"PLC.Symbols.{key[1]}")) for key in WATCHED]
        self._states = [(name, [node(name, f"PLC.Status.{what}")
                                for what in ("State", "FaultReason")]) for name in STATES]
        self._belts = [node("transport", f"PLC.Symbols.{sym}") for sym in BELTS]
        self._end_feed = node("cell", "PLC.Symbols.end_feed")
        return self

    async def end_feed(self) -> None:
        await self._end_feed.write_value(ua.Variant(True, ua.VariantType.Boolean))

    async def __aexit__(self, *exc: object) -> None:
        for client in self.clients.values():
            await client.disconnect()

    async def sample(self) -> Sample:
        values = {key: int(await node.read_value()) for key, node in self._values}
        states = {}
        for name, (state, reason) in self._states:
            text = str(await state.read_value())
            if text == "FAULTED":
                text += f" ({await reason.read_value()})"
            states[name] = text
        belts = [await node.read_value() for node in self._belts]
        return Sample(round(time.monotonic() - self.began, 2), values, states, not any(belts))


async def watch(run: CellRun, parts: int, timeout_s: float,
                say: Callable[[str], None] = print, poll_s: float = 0.2) -> CellReport:
    """Sample (printing each change) until the transport delivered `parts` parts, then end the
    feed through the cell's HMI bit and sample until the cell is drained: every part taken on
    delivered and drilled. Gives up after timeout_s; the report says how far it got."""
    report = CellReport()
    async with Watcher(run) as watcher:
        before: Sample | None = None
        uncertain = False
        while time.monotonic() - watcher.began < timeout_s:
            try:
                now = await watcher.sample()
            except ua.UaStatusCodeError as exc:
                if not ua.StatusCode(exc.code).is_uncertain():
                    raise
                # A PLC's snapshot went stale (its scan paused or starved): the server says
                # so with the last usable value; no sample now, look again (said once).
                if not uncertain:
                    say(f"t={time.monotonic() - watcher.began:7.2f}s  values uncertain "
                        f"({ua.StatusCode(exc.code).name}): waiting for fresh ones")
                uncertain = True
                await asyncio.sleep(poll_s)
                continue
            uncertain = False
            _record(report, before, now, say)
            before = report.last = now
            if not report.feed_ended and len(report.delivered_at) >= parts:
                await watcher.end_feed()
                report.feed_ended = True
                say(f"t={now.t_s:7.2f}s  end of feed (cell.end_feed=1)")
            elif report.feed_ended and now.drained():
                report.drained = True
                break
            await asyncio.sleep(poll_s)
    return report


def _record(report: CellReport, before: Sample | None, now: Sample,
            say: Callable[[str], None]) -> None:
    changed = [f"{plc}.{sym}={v}" for (plc, sym), v in now.values.items()
               if before is None or before.values[(plc, sym)] != v]
    changed += [f"{plc}:{state}" for plc, state in now.states.items()
                if before is None or before.states[plc] != state]
    if changed:
        say(f"t={now.t_s:7.2f}s  " + "  ".join(changed))
    delivered = now.values[("transport", "parts_delivered")]
    drilled = now.values[("drilling", "parts_drilled")]
    report.delivered_at += [now.t_s] * (delivered - len(report.delivered_at))
    report.drilled_at += [now.t_s] * (drilled - len(report.drilled_at))
    report.faults += [f"t={now.t_s}s: {plc} {state}" for plc, state in now.states.items()
                      if state.startswith("FAULTED") and (before is None
                                                           or before.states[plc] != state)]
    if drilled > delivered:
        report.breaches.append(f"t={now.t_s}s: {drilled} drilled but {delivered} delivered")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softplc.opcua.cell", description=__doc__)
    parser.add_argument("--parts", type=int, default=2, help="parts to deliver and drill (2)")
    parser.add_argument("--timeout", type=float, default=180.0, help="seconds (180)")
    parser.add_argument("--dir", default="state/cell", help="state dirs of the three PLCs")
    args = parser.parse_args(argv)
    with CellRun(Path(args.dir).resolve()) as run:
        report = asyncio.run(watch(run, args.parts, args.timeout))
    print(f"parts delivered {len(report.delivered_at)}, drilled {len(report.drilled_at)}, "
          f"drained {report.drained}; worst delivery-to-drilled {report.worst_lag_s():.1f} s; "
          f"breaches {len(report.breaches)}, faults {report.faults}")
    return 0 if report.drained and not report.breaches and not report.faults else 1


if __name__ == "__main__":
    sys.exit(main())
