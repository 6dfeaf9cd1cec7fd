"""Time for the runtime: the real monotonic clock and a virtual clock.

Owns: the Clock protocol, MonotonicClock (the real clock of the scan: the scan time `now_ns`
handed to the core is read here, or from a VirtualClock), VirtualClock (jumps to each
deadline; simulation and tests), Schedule (absolute deadlines, skipped slots). Durations
written as text: core/units.py, the one parser. Other code reads time.monotonic directly
for what never reaches the scan's semantics: timeouts and deadlines of commands and
connections, the age of a snapshot, I/O threads' backoff, benchmarks.
Does not know: scans, programs, processes.
"""

from __future__ import annotations

import select
import time
from typing import Protocol


class Clock(Protocol):
    """Nanoseconds on a monotonic time line, and a way to wait for a point on it."""

    def now_ns(self) -> int: ...

    def wait_until(self, deadline_ns: int) -> int:
        """Return at or after `deadline_ns` (at once if it has passed); return the time reached."""
        ...


class MonotonicClock:
    """The host's monotonic clock: coarse sleep, then a busy spin for the last `spin_ns`.

    `time.monotonic_ns` rather than `perf_counter_ns`: both are CLOCK_MONOTONIC with 1 ns
    resolution on Linux, but only `monotonic` is documented as system-wide, so deadlines can
    be compared between the scan and the communication process. `time.sleep` wakes 50-100 µs
    late on a stock kernel; spinning through the final 200 µs keeps lateness in the low
    microseconds at the cost of that much CPU per scan.

    `busy`: no sleep at all. The coarse part spins too, letting go of the interpreter lock at
    every turn (a select() with no timeout: other threads of the process may take the lock,
    but the CPU is not given away). On a virtual machine a sleeping virtual CPU halts, and
    the hypervisor wakes it up to several ms late: measured here, an empty 1 ms loop missed
    0-27 slots in 8 s sleeping and 0 busy (BENCHMARKS.md, online_change floor). Not
    sched_yield(): it handed the CPU to any runnable task there, the background compile
    process included, for a whole time slice (slots missed 3 ms late).
    """

    __slots__ = ("busy", "spin_ns")

    def __init__(self, spin_ns: int = 200_000, busy: bool = False) -> None:
        if spin_ns < 0:
            raise ValueError(f"spin_ns must be >= 0, got {spin_ns}")
        self.spin_ns = spin_ns
        self.busy = busy

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def wait_until(self, deadline_ns: int) -> int:
        now = time.monotonic_ns()
        coarse_until = deadline_ns - self.spin_ns
        if self.busy:
            while now < coarse_until:
                select.select((), (), (), 0)  # lets other threads have the lock, not the CPU
                now = time.monotonic_ns()
        elif coarse_until > now:
            time.sleep((coarse_until - now) / 1e9)
            now = time.monotonic_ns()
        while now < deadline_ns:
            now = time.monotonic_ns()
        return now


class Schedule:
    """Absolute deadlines start + k x period on `clock`. A scan that runs past the next
    deadline skips the slots it overlapped (counted, never caught up), so no drift builds up.
    The scan loop and the benchmark's empty-loop floor share it: the same scheduler."""

    __slots__ = ("clock", "k", "period_ns", "start_ns")

    def __init__(self, clock: Clock, period_ns: int) -> None:
        self.clock, self.period_ns = clock, period_ns
        self.start_ns, self.k = clock.now_ns(), 0

    @property
    def deadline_ns(self) -> int:
        return self.start_ns + self.k * self.period_ns

    def wait(self) -> int:
        """Wait for the current slot's deadline; the time reached."""
        return self.clock.wait_until(self.deadline_ns)

    def advance(self, done_ns: int) -> int:
        """Past the slot that ended at `done_ns`; the whole slots it ran past (0: on time)."""
        self.k += 1
        late = done_ns - self.deadline_ns
        skipped = late // self.period_ns + 1 if late > 0 else 0
        self.k += skipped
        return skipped


class VirtualClock:
    """Time that only moves when waited on: wait_until jumps straight to the deadline."""

    __slots__ = ("_now_ns",)

    def __init__(self, start_ns: int = 0) -> None:
        self._now_ns = start_ns

    def now_ns(self) -> int:
        return self._now_ns

    def wait_until(self, deadline_ns: int) -> int:
        # A deadline in the past is "late", like on the real clock: time never goes back.
        self._now_ns = max(self._now_ns, deadline_ns)
        return self._now_ns

    def advance(self, delta_ns: int) -> int:
        """Move time forward by `delta_ns` (>= 0), as if a scan had taken that long."""
        if delta_ns < 0:
            raise ValueError(f"a virtual clock cannot go back ({delta_ns} ns)")
        self._now_ns += delta_ns
        return self._now_ns
