"""Downloads compile off the scan (runtime/downloads.py): the scan goes on while a program
compiles, commands apply in the order they were sent, refusals keep every problem, and the
GIL switch interval is short only while a compile runs."""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.problems import ProgramError
from softplc.core.snapshot import CommandRequest
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime.downloads import (
    COMPILE_SWITCH_INTERVAL_S,
    Decided,
    DownloadQueue,
    ScanPace,
)

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = ROOT / "programs" / "transport.yaml"


def gated_compiler(gate: threading.Event):  # type: ignore[no-untyped-def]
    """The real compiler, held until `gate` opens (a big program takes seconds)."""

    def compile_program(request: CommandRequest) -> CompiledNet:
        assert gate.wait(10)
        return compile_text(request.program_text or "", str(TRANSPORT), ROOT)

    return compile_program


def take_until(queue: DownloadQueue, count: int, timeout_s: float = 10.0) -> list[Decided]:
    decided: list[Decided] = []
    deadline = time.monotonic() + timeout_s
    while len(decided) < count and time.monotonic() < deadline:
        decided += queue.take()
        time.sleep(0.001)
    return decided


def test_commands_behind_a_compiling_download_wait_and_keep_their_order() -> None:
    gate = threading.Event()
    queue = DownloadQueue(gated_compiler(gate))
    text = TRANSPORT.read_text()
    queue.put([CommandRequest(1, Command.STOP), CommandRequest(2, Command.DOWNLOAD,
                                                               program_text=text),
               CommandRequest(3, Command.START)])
    try:
        first = queue.take()
        assert [d.request.id for d in first] == [1]  # before the download: at once
        assert queue.take() == [] and queue.waiting == 2  # START waits for the download
        assert abs(sys.getswitchinterval() - COMPILE_SWITCH_INTERVAL_S) < 1e-6
        gate.set()
        rest = take_until(queue, 2)
        assert [d.request.id for d in rest] == [2, 3]
        assert rest[0].net is not None and rest[0].net.name == compile_file(TRANSPORT).name
        assert rest[1].net is None and rest[1].error is None
        assert sys.getswitchinterval() > 10 * COMPILE_SWITCH_INTERVAL_S
    finally:
        gate.set()
        queue.close()


def test_a_refused_download_carries_the_compiler_problems() -> None:
    queue = DownloadQueue(lambda req: compile_text(req.program_text or "", "bad.yaml", ROOT))
    queue.put([CommandRequest(5, Command.DOWNLOAD, program_text="program: x\nplaces: [\n")])
    try:
        (decided,) = take_until(queue, 1)
        assert isinstance(decided.error, ProgramError)
        assert "bad.yaml:" in str(decided.error)
    finally:
        queue.close()


def test_the_scan_loop_keeps_scanning_while_a_download_compiles(tmp_path: Path) -> None:
    from softplc.runtime.channel import Channel
    from softplc.runtime.clock import VirtualClock
    from softplc.runtime.loop import LoopConfig, ScanLoop

    gate = threading.Event()
    channel = Channel()
    loop = ScanLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT)), channel,
                    None, VirtualClock(0))
    loop.downloads = DownloadQueue(gated_compiler(gate))
    replies = []
    sender = threading.Thread(target=lambda: replies.append(channel.send_command(
        CommandRequest(9, Command.DOWNLOAD, program_text=TRANSPORT.read_text(), online=True),
        timeout_s=20)))
    sender.start()
    try:
        deadline = time.monotonic() + 10
        while loop.downloads.waiting == 0 and time.monotonic() < deadline:
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
        before = loop.runner.plc.scan_count
        for _ in range(20):  # the compile is held: the PLC goes on scanning its program
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
        assert loop.runner.plc.scan_count == before + 20 and not replies
        gate.set()
        while not replies and time.monotonic() < deadline:
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
            sender.join(0.001)
        assert replies and replies[0].ok, replies
    finally:
        gate.set()
        sender.join(10)
        loop.shutdown()


def test_a_replaced_net_is_let_go_of_on_the_compile_thread_not_the_scan_thread() -> None:
    """An online change: the old net's engine (and the net with it) is freed by the compile
    thread, a container at a time, after the swap scan; never by the scan thread, where a
    10,000-transition net's decref cascade took 7.4 ms."""
    import weakref

    from softplc.runtime.channel import Channel
    from softplc.runtime.clock import VirtualClock
    from softplc.runtime.loop import LoopConfig, ScanLoop

    channel = Channel()
    loop = ScanLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT)), channel,
                    None, VirtualClock(0))
    freed_on: list[str] = []
    try:
        for _ in range(3):
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
        engine = loop.runner.plc.engine
        assert engine is not None
        watch = weakref.ref(engine, lambda _: freed_on.append(threading.current_thread().name))
        del engine
        variant = TRANSPORT.read_text() + "\n# variant\n"
        replies = []
        sender = threading.Thread(target=lambda: replies.append(channel.send_command(
            CommandRequest(9, Command.DOWNLOAD, program_text=variant, online=True),
            timeout_s=20)))
        sender.start()
        deadline = time.monotonic() + 20
        while (watch() is not None or not replies) and time.monotonic() < deadline:
            loop.scan_once(loop.clock.now_ns())
            loop.clock.advance(10_000_000)
            sender.join(0.001)
        assert replies and replies[0].ok, replies
        assert loop.runner.plc.engine is not None and watch() is None
        assert freed_on and freed_on[0].startswith("compile"), freed_on
    finally:
        loop.shutdown()


def counting_compile(calls: list[int], started: threading.Event, until: int = 200_000):  # type: ignore[no-untyped-def]
    """A compile made of Python calls (each one a point where the pace may park it)."""

    def step() -> None:
        calls[0] += 1

    def compile_program(request: CommandRequest) -> str:
        started.set()
        while calls[0] < until:
            step()
        return "compiled"

    return compile_program


def parked(calls: list[int]) -> bool:
    """No progress over 0.1 s, after 0.05 s to reach the next call."""
    time.sleep(0.05)
    before = calls[0]
    time.sleep(0.1)
    return calls[0] == before


def test_a_compile_parks_while_a_scan_runs_and_goes_on_when_it_waits() -> None:
    calls, started = [0], threading.Event()
    pace = ScanPace(time.monotonic_ns)
    queue = DownloadQueue(counting_compile(calls, started), pace=pace)
    queue.put([CommandRequest(1, Command.DOWNLOAD, program_text="-")])
    try:
        assert started.wait(10)
        pace.scanning()
        assert parked(calls) and calls[0] < 200_000
        pace.waiting(time.monotonic_ns() + 60_000_000_000)
        assert [d.net for d in take_until(queue, 1)] == ["compiled"]
        assert sys.gettrace() is None  # the hook is the compile thread's alone
    finally:
        queue.close()


def test_a_compile_parks_by_itself_before_the_next_slot() -> None:
    """The scan thread is asleep until its deadline; the compile must let go of the
    interpreter `margin` before it, without being told."""
    calls, started = [0], threading.Event()
    pace = ScanPace(time.monotonic_ns, margin_ns=20_000_000)
    queue = DownloadQueue(counting_compile(calls, started, until=10**9), pace=pace)
    pace.waiting(time.monotonic_ns() + 60_000_000_000)
    queue.put([CommandRequest(1, Command.DOWNLOAD, program_text="-")])
    try:
        assert started.wait(10)
        slot = time.monotonic_ns() + 400_000_000  # the next slot in 400 ms, margin 20 ms
        pace.waiting(slot)
        before = calls[0]
        while calls[0] == before and time.monotonic_ns() < slot - 30_000_000:
            time.sleep(0.001)
        assert calls[0] > before  # it runs before the deadline
        time.sleep(max(0.0, (slot - time.monotonic_ns()) / 1e9))
        assert parked(calls)  # parked from 380 ms on, with nobody saying so
    finally:
        queue.close()


def test_an_open_pace_never_parks() -> None:
    """A loop on a virtual clock (tests) has an open pace: scanning() stops nothing."""
    calls, started = [0], threading.Event()
    queue = DownloadQueue(counting_compile(calls, started))
    queue.put([CommandRequest(1, Command.DOWNLOAD, program_text="-")])
    try:
        assert started.wait(10)
        queue.pace.scanning()
        assert [d.net for d in take_until(queue, 1)] == ["compiled"]
    finally:
        queue.close()


def test_closing_the_queue_releases_a_compile_parked_on_a_scan() -> None:
    calls, started = [0], threading.Event()
    pace = ScanPace(time.monotonic_ns)
    queue = DownloadQueue(counting_compile(calls, started), pace=pace)
    queue.put([CommandRequest(1, Command.DOWNLOAD, program_text="-")])
    assert started.wait(10)
    pace.scanning()
    assert parked(calls)
    queue.close()  # the loop's shutdown: no scan will come again
    deadline = time.monotonic() + 10
    while calls[0] < 200_000 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert calls[0] == 200_000
