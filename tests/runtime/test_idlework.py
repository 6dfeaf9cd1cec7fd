"""Work done on the scan thread between scans (runtime/idlework.py): steps run only while
they end before the slot, results and failures reach the thread that asked, nothing is left
hanging when the loop ends; and in a real scan loop, an online change's net, engine and
carry plan are built on the scan thread, the replaced net freed there too."""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command
from softplc.core.snapshot import CommandRequest
from softplc.core.steps import Steps, drain
from softplc.runtime.idlework import STEP_NS, IdleWork, LoopEnded

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = ROOT / "programs" / "transport.yaml"


class TickClock:
    """Each reading is `tick` ns after the last: a step costs one tick."""

    def __init__(self, tick: int) -> None:
        self.t, self.tick = 0, tick

    def __call__(self) -> int:
        self.t += self.tick
        return self.t


def counting(n: int, done: list[int]) -> Steps[int]:
    for i in range(n):
        done.append(i)
        yield
    return n * 10


def test_steps_run_only_while_one_still_ends_before_the_limit() -> None:
    clock = TickClock(100_000)  # each step (one reading) costs 100 µs
    work = IdleWork(clock)
    done: list[int] = []
    future = work.submit(counting(50, done))
    work.run(until_ns=clock.t + STEP_NS + 500_000)
    assert 1 <= len(done) <= 5  # never a step started within STEP_NS of the limit
    assert not future.done()
    work.run(until_ns=clock.t)  # no time left: no step at all
    assert len(done) <= 5
    while not future.done():
        work.run(until_ns=clock.t + 10**9)
    assert future.result() == 500 and done == list(range(50)) and work.pending == 0


def test_a_failing_step_goes_to_its_requester_and_the_next_job_runs() -> None:
    work = IdleWork(time.monotonic_ns)

    def failing() -> Steps[None]:
        yield
        raise ValueError("bad piece")

    bad = work.submit(failing())
    good = work.submit(counting(3, []))
    work.run(time.monotonic_ns() + 10**9)  # raises nothing here, on the scan thread
    with pytest.raises(ValueError, match="bad piece"):
        bad.result(0)
    assert good.result(0) == 30


def test_finish_waits_for_the_scan_thread_and_returns_its_result() -> None:
    work = IdleWork(time.monotonic_ns)
    stepped_on: set[str] = set()

    def job() -> Steps[str]:
        for _ in range(5):
            stepped_on.add(threading.current_thread().name)
            yield
        return "built"

    got: list[str] = []
    work.start()
    asker = threading.Thread(target=lambda: got.append(work.finish(job())), name="compile")
    asker.start()
    deadline = time.monotonic() + 10
    while asker.is_alive() and time.monotonic() < deadline:
        work.run(time.monotonic_ns() + 10**9)
        asker.join(0.001)
    assert got == ["built"] and stepped_on == {threading.current_thread().name}


def test_closing_tells_whoever_waits_and_refuses_later_work() -> None:
    clock = TickClock(1)
    work = IdleWork(clock)
    closed: list[bool] = []

    def job() -> Iterator[None]:
        try:
            yield
            yield
        finally:
            closed.append(True)

    future = work.submit(job())  # type: ignore[arg-type]
    work.run(clock.t + STEP_NS + 2)  # one step: the job is under way
    assert not closed
    work.close()
    with pytest.raises(LoopEnded):
        future.result(0)
    with pytest.raises(LoopEnded):
        work.submit(counting(1, [])).result(0)
    assert work.pending == 0 and closed == [True]  # its generator was closed, not left open


def test_drain_runs_every_step_and_returns_the_result() -> None:
    done: list[int] = []
    assert drain(counting(4, done)) == 40 and done == [0, 1, 2, 3]


def test_without_a_running_loop_the_steps_run_where_they_are_asked_for() -> None:
    work = IdleWork(time.monotonic_ns)  # never started: a loop scanned by hand
    assert work.finish(counting(3, [])) == 30 and work.pending == 0
    work.start()
    work.close()
    assert not work.active and work.finish(counting(2, [])) == 20


def test_an_online_change_is_built_and_the_old_net_freed_on_the_scan_thread() -> None:
    """A real loop on the monotonic clock (compile process included): the download's last
    part (load, engine, carry plan) and the burial of the replaced net run on the scan
    thread, a step at a time between scans, never on the compile thread."""
    from softplc.runtime.channel import Channel
    from softplc.runtime.loop import LoopConfig, ScanLoop

    channel = Channel()
    loop = ScanLoop(LoopConfig(program=str(TRANSPORT), start=True, root=str(ROOT),
                               period_ns=2_000_000), channel, None)
    stepped_on: set[str] = set()
    finishing = loop.prep._finishing

    def spy(*args):  # type: ignore[no-untyped-def]
        steps = finishing(*args)
        while True:
            stepped_on.add(threading.current_thread().name)
            try:
                next(steps)
            except StopIteration as done:
                return done.value
            yield

    loop.prep._finishing = spy  # type: ignore[method-assign]
    stop = threading.Event()
    scan = threading.Thread(target=loop.run, args=(stop,), name="scan")
    scan.start()
    freed_on: list[str] = []
    try:
        deadline = time.monotonic() + 20
        while loop.runner.plc.engine is None and time.monotonic() < deadline:
            time.sleep(0.01)
        engine = loop.runner.plc.engine
        assert engine is not None
        watch = weakref.ref(engine, lambda _: freed_on.append(threading.current_thread().name))
        del engine
        reply = channel.send_command(CommandRequest(
            9, Command.DOWNLOAD, program_text=TRANSPORT.read_text() + "\n# variant\n",
            online=True), timeout_s=30)
        assert reply.ok, reply.message
        while watch() is not None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert watch() is None and freed_on == ["scan"]
        assert stepped_on == {"scan"}
        assert loop.compiler is not None and loop.compiler.started == 1
    finally:
        stop.set()
        scan.join(10)
