"""A dry run's answer is built off the scan (runtime/download.py, stage DESCRIBING): at its
turn the scan only copies the PLC; the carry plan, its description and the verdict are
stepped between scans from that copy; the reply keeps its place among the other commands'.
A download whose carry plan was made against a net no longer running is planned again
between scans, not in the swap scan (issue 28, item 4)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from softplc.core import online
from softplc.core.judge import NOTHING_OBSERVED, Observed
from softplc.core.lifecycle import Command, PlcState
from softplc.core.net import CompiledNet
from softplc.core.snapshot import CommandReply, CommandRequest, Refusal
from softplc.core.steps import Steps
from softplc.program.compiler import compile_file
from softplc.runtime.config import LoopConfig
from softplc.runtime.download import Downloads, Stage, refusal_of
from softplc.runtime.loop import ScanLoop
from softplc.runtime.prepare import Prepared, Preparer
from softplc.runtime.shared.channel import Channel

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = ROOT / "programs" / "transport.yaml"


class WatchedLoop(ScanLoop):
    """A loop that says whether its thread is inside a scan right now."""

    in_scan = False

    def scan_once(self, now_ns: int, observed: Observed = NOTHING_OBSERVED) -> bool:
        self.in_scan = True
        try:
            return super().scan_once(now_ns, observed)
        finally:
            self.in_scan = False


def called(work: Callable[..., Any], loop: WatchedLoop, seen: list[bool]) -> Callable[..., Any]:
    """`work` (a plain call of core/online.py), noting whether it ran inside a scan."""
    def wrapper(*args: Any) -> Any:
        seen.append(loop.in_scan)
        return work(*args)
    return wrapper


def stepped(work: Callable[..., Steps[Any]], loop: WatchedLoop, seen: list[bool]
            ) -> Callable[..., Steps[Any]]:
    """`work` (a generator function of core/online.py), noting for each of its steps whether
    it ran inside a scan."""
    def wrapper(*args: Any) -> Steps[Any]:
        steps = work(*args)
        while True:
            seen.append(loop.in_scan)
            try:
                next(steps)
            except StopIteration as done:
                return done.value
            yield
    return wrapper


def test_a_dry_run_is_described_between_scans_and_answered_in_order(
        monkeypatch: pytest.MonkeyPatch) -> None:
    channel = Channel()
    loop = WatchedLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                                  period_ns=10_000_000), channel, None)
    seen: list[bool] = []
    for name in ("describe", "plan"):  # the plain calls (the old way: inside the scan)
        monkeypatch.setattr(online, name, called(getattr(online, name), loop, seen))
    for name in ("describing", "planning"):  # the steps (the old code had no `describing`)
        if hasattr(online, name):
                monkeypatch.setattr(online, name, stepped(getattr(online, name), loop, seen))
    sent: list[int] = []
    reply_to = channel.reply

    def reply(answer: CommandReply, later: bool = False) -> None:
        if not later:  # sent now (a held reply comes back through here when it is sent)
            sent.append(answer.id)
        reply_to(answer, later=later)
    monkeypatch.setattr(channel, "reply", reply)
    stop = threading.Event()
    thread = threading.Thread(target=loop.run, args=(stop,), daemon=True)
    thread.start()
    replies: dict[int, CommandReply] = {}

    def send(request: CommandRequest) -> threading.Thread:
        def run() -> None:
            replies[request.id] = channel.send_command(request, timeout_s=60)
        sender = threading.Thread(target=run, daemon=True)
        sender.start()
        return sender

    try:
        first = send(CommandRequest(1, Command.DOWNLOAD, program_text=TRANSPORT.read_text(),
                                    program_path=str(TRANSPORT), online=True, dry_run=True))
        deadline = time.monotonic() + 30
        while loop.downloads.stage(1) is None and 1 not in replies \
                and time.monotonic() < deadline:
            time.sleep(0.001)
        second = send(CommandRequest(2, Command.UNFORCE))  # sent after it: answered after
        first.join(60)
        second.join(60)
        dry, after = replies[1], replies[2]
        assert dry.ok and dry.message.startswith("dry run: accepted"), dry
        assert dry.detail is not None and dry.detail["state"] == "RUNNING"
        assert dry.detail["from"] == dry.detail["to"] == compile_file(TRANSPORT).name
        assert dry.detail["dropped"] == {} and dry.detail["new"] == {}
        assert dry.detail["kept"] and dry.detail["accepted"]
        assert after.ok and after.state is PlcState.RUNNING, after
        assert sent == [1, 2], sent
        assert seen and not any(seen), seen  # described, and never inside a scan
    finally:
        stop.set()
        thread.join(30)


def describing_slowly(prepared: Prepared, steps: int = 1_000) -> Steps[CommandReply]:
    """A dry run's answer that takes many steps (as a big net's would)."""
    for _ in range(steps):
        yield
    return CommandReply(prepared.request.id, True, "dry run: accepted (nothing applied)",
                        PlcState.RUNNING)


def ready_downloads(requests: list[CommandRequest], running: list[CompiledNet]) -> Downloads:
    """Downloads (stepped as between scans) with `requests` put and prepared to READY."""
    prep = Preparer(LoopConfig(root=str(ROOT)), lambda: running[0],
                    lambda: tuple(running[0].io.drivers.values()))
    downloads = Downloads(prep)
    downloads.put(requests)
    downloads.work(None, time.monotonic_ns)
    for request in requests:
        assert downloads.stage(request.id) in (Stage.READY, None)
    return downloads


def dry(request_id: int) -> CommandRequest:
    return CommandRequest(request_id, Command.DOWNLOAD, program_text=TRANSPORT.read_text(),
                          program_path=str(TRANSPORT), online=True, dry_run=True)


def test_commands_after_a_dry_run_wait_for_its_answer() -> None:
    running = [compile_file(TRANSPORT, ROOT)]
    downloads = ready_downloads([dry(1), CommandRequest(2, Command.RESET)], running)
    try:
        assert downloads.take(describing_slowly) == []  # its turn: described from now on
        assert downloads.stage(1) is Stage.DESCRIBING and downloads.busy
        downloads.work(time.monotonic_ns() + 100_000_000, time.monotonic_ns)
        (answer, reset) = downloads.take(describing_slowly)
        assert answer.reply is not None and answer.reply.id == 1
        assert reset.request.id == 2 and reset.reply is None
    finally:
        downloads.close()


def test_a_stop_withdraws_a_dry_run_being_described_and_keeps_the_order() -> None:
    running = [compile_file(TRANSPORT, ROOT)]
    downloads = ready_downloads([dry(1), CommandRequest(2, Command.RESET)], running)
    try:
        assert downloads.take(describing_slowly) == []
        downloads.put([CommandRequest(3, Command.STOP)])
        withdrawn, reset, stop = downloads.take(describing_slowly)  # nothing held
        assert [withdrawn.request.id, reset.request.id, stop.request.id] == [1, 2, 3]
        assert withdrawn.reply is None
        kind, _, _ = refusal_of(withdrawn.error or RuntimeError(), str)
        assert kind is Refusal.WITHDRAWN
    finally:
        downloads.close()


def test_a_carry_plan_made_against_a_replaced_net_is_made_again_between_scans() -> None:
    """Two online changes queued together: the second was planned against the net the first
    replaces. It is handed out at a later boundary, planned again against the net running
    then, so that the swap scan does not plan (online.plan on the scan: ~12 ms for 16,000
    places)."""
    first = compile_file(TRANSPORT, ROOT)
    running = [first]
    variant = TRANSPORT.read_text() + "\n# variant\n"
    downloads = ready_downloads([
        CommandRequest(1, Command.DOWNLOAD, program_text=variant, program_path=str(TRANSPORT),
                       online=True),
        CommandRequest(2, Command.DOWNLOAD, program_text=variant, program_path=str(TRANSPORT),
                       online=True),
        CommandRequest(3, Command.RESET)], running)
    try:
        (one,) = downloads.take()  # one download per boundary: the next is planned after it
        assert one.prepared is not None and one.prepared.plan is not None
        assert one.prepared.plan.old is first
        running[0] = one.prepared.net  # applied in that scan
        assert downloads.take() == []
        assert downloads.stage(2) is Stage.PLANNING
        downloads.work(None, time.monotonic_ns)
        two, reset = downloads.take()
        assert two.prepared is not None and two.prepared.plan is not None
        assert two.prepared.plan.old is one.prepared.net and reset.request.id == 3
    finally:
        downloads.close()
