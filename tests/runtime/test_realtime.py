"""Real-time scheduling of the scan process: what is asked is what is reported, helper
threads go back to normal scheduling, and bad settings are refused up front. Each check runs
in a child process so that this test process keeps its own scheduling."""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import pytest

from softplc.runtime.realtime import (
    Realtime,
    apply,
    background_thread,
    keep_off_scan_cpu,
    share_interpreter,
)


def probe(rt: Realtime, out: Connection) -> None:
    said = apply(rt)
    seen: dict[str, object] = {}

    def helper() -> None:
        background_thread()
        seen["helper_policy"] = os.sched_getscheduler(0)
        seen["helper_cpus"] = sorted(os.sched_getaffinity(0))

    thread = threading.Thread(target=helper)
    thread.start()
    thread.join()
    out.send({"said": said, "policy": os.sched_getscheduler(0),
              "priority": os.sched_getparam(0).sched_priority,
              "cpus": sorted(os.sched_getaffinity(0)), **seen})


def run_probe(rt: Realtime) -> dict[str, object]:
    result: dict[str, object] = in_child(probe, rt)
    return result


def in_child(target: Callable[..., object], *args: object) -> Any:
    """`target(*args, out)` in a spawned child; what it sent on `out`."""
    ctx = mp.get_context("spawn")
    receiver, sender = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=target, args=(*args, sender))
    proc.start()
    try:
        assert receiver.poll(30)
        return receiver.recv()
    finally:
        proc.join(10)


def test_fifo_priority_and_cpu_are_applied_or_the_refusal_is_reported() -> None:
    cpu = max(os.sched_getaffinity(0))
    got = run_probe(Realtime(priority=50, cpu=cpu))
    if got["policy"] == os.SCHED_FIFO:
        assert got["priority"] == 50
        assert str(got["said"]).startswith("SCHED_FIFO priority 50")
    else:  # no CAP_SYS_NICE here: said so, and the PLC runs anyway
        assert "SCHED_FIFO refused" in str(got["said"])
    assert got["cpus"] == [cpu] and f"pinned to CPU {cpu}" in str(got["said"])
    # the compiler and retain threads must not compete with the scan as FIFO on its CPU
    assert got["helper_policy"] == os.SCHED_OTHER
    assert len(got["helper_cpus"]) == os.cpu_count()  # type: ignore[arg-type]


def test_normal_scheduling_changes_nothing() -> None:
    got = run_probe(Realtime())
    assert got["said"] == "normal scheduling" and got["policy"] == os.SCHED_OTHER


def test_a_busy_wait_is_said_and_refused_with_a_fifo_priority() -> None:
    got = run_probe(Realtime(busy_wait=True))
    assert got["said"] == "busy wait" and got["policy"] == os.SCHED_OTHER
    with pytest.raises(ValueError, match="choose one"):
        Realtime(priority=10, busy_wait=True)


def pinned_starter(cpu: int, out: Connection) -> None:
    """As the scan process does: pinned to its CPU, it starts the compile process."""
    os.sched_setaffinity(0, {cpu})
    ctx = mp.get_context("spawn")
    child = ctx.Process(target=time.sleep, args=(5,))
    child.start()
    assert child.pid is not None
    keep_off_scan_cpu(child.pid, Realtime(cpu=cpu))
    out.send(sorted(os.sched_getaffinity(child.pid)))
    child.kill()
    child.join(5)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs")
def test_a_pinned_scan_process_keeps_its_children_off_its_cpu() -> None:
    """The compile process, started by the pinned scan process, inherits its one CPU;
    it must go to the others (found with --busy-wait --scan-cpu: the compile process sat
    starved on the scan's CPU)."""
    cpu = max(os.sched_getaffinity(0))
    cpus = in_child(pinned_starter, cpu)
    assert cpus and cpu not in cpus


@pytest.mark.parametrize("kwargs", [{"priority": 0}, {"priority": 100},
                                    {"cpu": 10_000}])
def test_bad_settings_are_refused_with_the_allowed_range(kwargs: dict[str, int]) -> None:
    with pytest.raises(ValueError, match=r"1..99|not available"):
        Realtime(**kwargs)


def test_run_refuses_busy_wait_with_a_fifo_priority_before_starting_anything(
        capsys: pytest.CaptureFixture[str]) -> None:
    from pathlib import Path

    from softplc.cli import main
    from softplc.runtime.supervise.runcmd import EXIT_USAGE

    program = Path(__file__).resolve().parents[2] / "programs" / "transport.yaml"
    code = main(["run", str(program), "--busy-wait", "--rt-priority", "10",
                 "--modbus", "127.0.0.1:0", "--api", "127.0.0.1:0"])
    assert code == EXIT_USAGE
    assert "--busy-wait with --rt-priority" in capsys.readouterr().err


def switch_probe(periods: list[int], out: Connection) -> None:
    seen = []
    for period_ns in periods:
        said = share_interpreter(period_ns)
        seen.append((said, sys.getswitchinterval()))
    out.send(seen)


def test_the_scan_process_lets_a_helper_thread_hold_it_off_a_fifth_of_a_period_at_most() -> None:
    """A thread holding the interpreter lock keeps the scan waiting up to the switch interval
    (CPython's 5 ms: several slots at 1 ms): a fifth of the period, 50 us..5 ms, said."""
    got = in_child(switch_probe, [1_000_000, 10_000_000, 100_000_000, 100_000])
    assert [round(seconds * 1e6) for _, seconds in got] == [200, 2000, 5000, 50]
    assert [said for said, _ in got] == [
        "interpreter switch interval 0.2 ms", "interpreter switch interval 2 ms",
        "interpreter switch interval 5 ms", "interpreter switch interval 0.05 ms"]
