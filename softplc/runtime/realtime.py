"""Real-time scheduling of the scan process: SCHED_FIFO priority and a CPU of its own.

Owns: applying a priority and CPU pinning to the calling process and saying what it got.
What soft PLCs on Linux do (CODESYS, OpenPLC's RT patches): a FIFO priority lets the scan
preempt Modbus, HTTP and everything else on its CPU the moment its deadline comes. Refusal
(no CAP_SYS_NICE, a container) is reported, never fatal: the PLC runs at normal priority.
Does not know: the scan loop.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Realtime:
    priority: int | None = None  # SCHED_FIFO 1..99; None: normal scheduling
    cpu: int | None = None  # pin the scan to this CPU; None: any CPU
    # Wait for each slot without sleeping (runtime/clock.py): the scan's CPU never halts, so
    # nothing has to wake it. For virtual machines, where waking a halted virtual CPU takes
    # the hypervisor up to several ms; it costs that CPU, always busy.
    busy_wait: bool = False

    def __post_init__(self) -> None:
        if self.priority is not None and not 1 <= self.priority <= 99:
            raise ValueError(f"a SCHED_FIFO priority is 1..99, got {self.priority}")
        if self.priority is not None and self.busy_wait:
            raise ValueError("--busy-wait with --rt-priority: a SCHED_FIFO scan that never "
                             "sleeps keeps every normal process off its CPU (the kernel's "
                             "real-time throttling then stops it for 50 ms a second); choose "
                             "one")
        if self.cpu is not None and self.cpu not in os.sched_getaffinity(0):
            raise ValueError(f"CPU {self.cpu} is not available; this process may use "
                             f"{sorted(os.sched_getaffinity(0))}")


NORMAL = Realtime()


def apply(rt: Realtime) -> str:
    """Apply `rt` to the calling process; what it runs with now, in words."""
    said = []
    if rt.cpu is not None:
        try:
            os.sched_setaffinity(0, {rt.cpu})
            said.append(f"pinned to CPU {rt.cpu}")
        except OSError as exc:
            said.append(f"CPU pinning refused ({exc.strerror})")
    if rt.priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt.priority))
            said.insert(0, f"SCHED_FIFO priority {rt.priority}")
        except OSError as exc:
            said.insert(0, f"normal scheduling (SCHED_FIFO refused: {exc.strerror})")
    if rt.busy_wait:
        said.append("busy wait")
    return ", ".join(said) or "normal scheduling"


def recommended() -> Realtime:
    """The benchmark's and the docs' deployment: FIFO 50 on the last CPU, if there are two."""
    cpus = sorted(os.sched_getaffinity(0))
    return Realtime(priority=50, cpu=cpus[-1] if len(cpus) > 1 else None)


def background_thread(rt: Realtime = NORMAL) -> None:
    """In a helper thread of the scan process (compiler, retain writer): back to normal
    scheduling on any CPU, but `rt`'s scan CPU. Linux threads inherit the creator's policy and
    CPU, and a FIFO helper on the scan's CPU would not yield to the scan when its deadline
    comes (nor a normal one to a busy-waiting scan for the rest of a tick)."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    except OSError:
        pass  # still the process's own policy: only as good as the scan's
    keep_off_scan_cpu(0, rt)  # 0: this thread


def keep_off_scan_cpu(pid: int, rt: Realtime) -> None:
    """Another process of the runtime (communication, HMI load): on every CPU but the scan's,
    so its work and the network stack's soft interrupts it causes stay off that CPU."""
    if rt.cpu is None:
        return
    # Every CPU of the machine, not the caller's: the scan process itself (pinned to its
    # CPU) starts the compile process. The kernel keeps a cpuset's limits.
    others = set(range(os.cpu_count() or 1)) - {rt.cpu}
    if others:  # on failure (process gone, not allowed) it shares the CPU, as unpinned
        with contextlib.suppress(OSError):
            os.sched_setaffinity(pid, others)
