"""Clock protocol implementations and duration parsing."""

from __future__ import annotations

import pytest

from softplc.runtime.clock import (
    Clock,
    MonotonicClock,
    Schedule,
    VirtualClock,
)


def test_monotonic_wait_until_never_returns_before_the_deadline() -> None:
    clock = MonotonicClock(spin_ns=100_000)
    for step_ns in (0, 50_000, 300_000, 1_000_000):
        deadline = clock.now_ns() + step_ns
        reached = clock.wait_until(deadline)
        assert reached >= deadline
        assert clock.now_ns() >= reached


def test_a_busy_wait_never_sleeps_yet_lets_other_threads_of_the_process_run() -> None:
    """--busy-wait: the waiting thread keeps its CPU busy where a sleeping wait uses almost
    none, and the interpreter lock is not kept: a helper thread of the process (the compile
    thread) gets through its work meanwhile."""
    import threading
    import time

    def cpu_of_a_wait(clock: MonotonicClock, wait_ns: int) -> int:
        before = time.thread_time_ns()
        clock.wait_until(clock.now_ns() + wait_ns)
        return time.thread_time_ns() - before

    sleeping = cpu_of_a_wait(MonotonicClock(), 100_000_000)
    busy = cpu_of_a_wait(MonotonicClock(busy=True), 100_000_000)
    assert busy > 10 * max(sleeping, 1_000_000)

    clock = MonotonicClock(busy=True)
    counted = [0]
    stop = threading.Event()

    def helper() -> None:
        while not stop.is_set():
            counted[0] += 1

    thread = threading.Thread(target=helper)
    thread.start()
    try:
        deadline = clock.now_ns() + 200_000_000
        counted[0] = 0
        reached = clock.wait_until(deadline)
    finally:
        stop.set()
        thread.join(5)
    assert reached >= deadline
    assert counted[0] > 10_000  # the helper ran while this thread waited


def test_monotonic_wait_until_a_past_deadline_returns_at_once() -> None:
    clock = MonotonicClock()
    now = clock.now_ns()
    assert clock.wait_until(now - 10**9) >= now


def test_monotonic_rejects_negative_spin() -> None:
    with pytest.raises(ValueError, match="spin_ns"):
        MonotonicClock(spin_ns=-1)


def test_virtual_clock_jumps_to_the_deadline_and_never_goes_back() -> None:
    clock: Clock = VirtualClock(start_ns=1_000)
    assert clock.now_ns() == 1_000
    assert clock.wait_until(5_000_000_000) == 5_000_000_000
    assert clock.now_ns() == 5_000_000_000
    assert clock.wait_until(10) == 5_000_000_000
    assert clock.now_ns() == 5_000_000_000


def test_virtual_clock_advance() -> None:
    clock = VirtualClock()
    assert clock.advance(250) == 250
    with pytest.raises(ValueError, match="cannot go back"):
        clock.advance(-1)


def test_schedule_skips_the_slots_a_long_scan_ran_past_and_never_drifts() -> None:
    clock = VirtualClock(1_000)
    schedule = Schedule(clock, 10)
    assert schedule.wait() == 1_000
    assert schedule.advance(1_005) == 0 and schedule.deadline_ns == 1_010  # on time
    assert schedule.advance(1_010) == 0 and schedule.deadline_ns == 1_020  # at the deadline
    assert schedule.advance(1_045) == 2 and schedule.deadline_ns == 1_050  # ran past 1030, 1040
    assert schedule.wait() == 1_050
