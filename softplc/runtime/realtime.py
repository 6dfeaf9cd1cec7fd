"""Real-time scheduling of the scan process: SCHED_FIFO priority and a CPU of its own.

Owns: applying a priority and CPU pinning to the calling process and saying what it got;
the interpreter's switch interval of the scan process (how long a helper thread may keep the
scan thread waiting for the interpreter lock); every other thread of the scan process kept
off the scan's CPU, its Python threads at the interpreter lock's priority ceiling and named
for `ps -L`, `top -H` and `perf` (HelperThreads: one sweep of the process's threads, whoever
started them).
What soft PLCs on Linux do (CODESYS, OpenPLC's RT patches): a FIFO priority lets the scan
preempt Modbus, HTTP and everything else on its CPU the moment its deadline comes. Refusal
(no CAP_SYS_NICE, a container) is reported, never fatal: the PLC runs at normal priority.
Does not know: the scan loop.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
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


def share_interpreter(period_ns: int) -> str:
    """Set the scan process's switch interval to a fifth of the period (50 us..5 ms) and say
    so. A thread that holds the interpreter lock (the download thread loading a reply or
    staging the boot program, a device's I/O thread, the retain writer) keeps the scan thread
    waiting until it blocks, or until this interval after the scan asked; at CPython's 5 ms a
    1 ms scan lost slots to each. Measured (a 1 ms loop pinned to CPU 1 beside a
    thread pinned to CPU 0 doing 3 ms of Python every 13 ms, 4 s, load 2-3): 239-242 slots
    started over 1 ms late at 5 ms, 41-48 at 0.2 ms, 40 with no such thread."""
    seconds = min(0.005, max(50e-6, period_ns / 5e9))
    sys.setswitchinterval(seconds)
    return f"interpreter switch interval {seconds * 1e3:g} ms"


def recommended() -> Realtime:
    """The benchmark's and the docs' deployment: FIFO 50 on the last CPU, if there are two."""
    cpus = sorted(os.sched_getaffinity(0))
    return Realtime(priority=50, cpu=cpus[-1] if len(cpus) > 1 else None)


def background_thread(rt: Realtime = NORMAL) -> None:
    """In a helper thread of the scan process (compiler, retain writer), as it starts: its
    place (`helper_policy`) on any CPU but `rt`'s scan CPU. Linux threads inherit the
    creator's policy and CPU, and a FIFO helper on the scan's CPU would not yield to the scan
    when its deadline comes (nor a normal one to a busy-waiting scan for the rest of a tick)."""
    _place(0, *helper_policy(rt))
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    keep_off_scan_cpu(0, rt)  # 0: this thread


# The interpreter lock's priority ceiling: the SCHED_FIFO priority of the scan process's
# Python threads but the scan's (HelperThreads).
CEILING = 1


def helper_policy(rt: Realtime) -> tuple[int, int]:
    """(policy, priority) of a Python thread of the scan process other than the scan thread.
    Such a thread holds the scan's interpreter lock whenever it runs Python: preempted
    meanwhile by a normal task (the compile process, the communication process), it kept
    the scan waiting at its deadline until it ran again (perf sched, issue 40 item 8: the
    download thread preempted for 3.0 ms by the compile process it had just woken, the
    scan 2.8 ms late). So they run at SCHED_FIFO CEILING, above every normal task and below
    the scan, whenever the scan has a CPU of its own or a FIFO priority above CEILING: the
    priority ceiling of real-time locks. Otherwise the scan itself is a normal task, and so
    are they."""
    if rt.cpu is not None or (rt.priority is not None and rt.priority > CEILING):
        return os.SCHED_FIFO, CEILING
    return os.SCHED_OTHER, 0


def _place(tid: int, policy: int, priority: int) -> str:
    """Thread `tid` (0: this one) at `policy`; "" or why it was refused (then at normal
    scheduling: a refused ceiling leaves it where any normal task is)."""
    try:
        os.sched_setscheduler(tid, policy, os.sched_param(priority))
        return ""
    except ProcessLookupError:
        return ""  # it ended meanwhile
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
        return exc.strerror or str(exc)


def keep_off_scan_cpu(pid: int, rt: Realtime) -> None:
    """Another process of the runtime (communication, HMI load), every thread of it (pid 0:
    the calling thread): on every CPU but the scan's, so its work and the network stack's
    soft interrupts it causes stay off that CPU. Every thread: the threads a process started
    before this call (numpy's, a server's) kept the CPUs they had, the scan's among them."""
    if rt.cpu is None:
        return
    for tid in _threads(pid) if pid else (0,):
        _off_scan_cpu(tid, rt.cpu)


def _threads(pid: int | str) -> list[int]:
    """The thread ids of process `pid` ("self": this one); without /proc, its main thread."""
    try:
        return [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:  # no /proc, or the process is gone
        return [os.getpid() if pid == "self" else int(pid)]


def _off_scan_cpu(tid: int, cpu: int) -> None:
    # Every CPU of the machine, not the caller's: the scan process itself (pinned to its
    # CPU) starts the compile process. The kernel keeps a cpuset's limits.
    others = set(range(os.cpu_count() or 1)) - {cpu}
    if others:  # on failure (thread gone, not allowed) it shares the CPU, as unpinned
        with contextlib.suppress(OSError):
            os.sched_setaffinity(tid, others)


class HelperThreads:
    """The scan process's other threads (the watchdog's, the download's, the retain and boot
    writers', a device's I/O thread, numpy's) inherit the scan thread's CPU and priority
    when it starts them: pinned, they ran on the scan's CPU, and under --rt-priority at its
    SCHED_FIFO priority, where one would not yield to the scan when its deadline comes
    (tests/runtime/test_helper_threads.py read both from /proc). `sweep()`, on the scan
    thread after a scan: every other thread of the process off the scan's CPU, its Python
    threads at `helper_policy` (the interpreter lock's ceiling) and named as Python names
    them (their /proc comm), the others (numpy's, C threads: they never hold the lock) at
    normal scheduling; again whenever the set of Python threads changed since the last
    sweep (one `threading.enumerate()`; the sweep reads /proc/self/task). `said`: how the
    Python threads run, in words, for status."""

    def __init__(self, rt: Realtime) -> None:
        self.rt = rt
        self.policy = helper_policy(rt)
        self.seen: frozenset[int | None] = frozenset({-1})  # never swept
        self.said = _said(*self.policy, "")

    def sweep(self) -> None:
        if self.rt.cpu is None and self.rt.priority is None:
            return  # nothing was applied to the scan thread: nothing to undo in the others
        python = {t.native_id: t.name for t in threading.enumerate()}
        if (now := frozenset(python)) == self.seen:
            return
        self.seen = now
        me, refused = threading.get_native_id(), ""
        for tid in _threads("self"):
            if tid == me:
                continue
            if tid in python:
                refused = _place(tid, *self.policy) or refused
                _name_thread(tid, python[tid])
            else:
                _place(tid, os.SCHED_OTHER, 0)
            if self.rt.cpu is not None:
                _off_scan_cpu(tid, self.rt.cpu)
        self.said = _said(*self.policy, refused)


def _said(policy: int, priority: int, refused: str) -> str:
    if refused:
        return f"helper threads at normal scheduling (SCHED_FIFO {priority} refused: {refused})"
    if policy == os.SCHED_FIFO:
        return f"helper threads at SCHED_FIFO {priority} (the interpreter lock's ceiling)"
    return "helper threads at normal scheduling"


def _name_thread(tid: int, name: str) -> None:
    """Thread `tid` of this process shown as `name` (its first 15 bytes) in /proc, `ps -L`,
    `top -H` and `perf`, where every thread showed as its process."""
    with contextlib.suppress(OSError), open(f"/proc/self/task/{tid}/comm", "wb") as comm:
        comm.write(name.encode()[:15])
