"""Where the isolation bench's clients run (isolationbench.py; BENCHMARKS.md, Isolation).

Owns: the CPUs and scheduling class of the measuring clients (the Modbus and HTTP pollers)
and of each abuser. In the field every client of the PLC is on another machine: what it
costs the PLC is what its requests cost the serving processes, never its own CPU. On this
machine (the scan on a CPU of its own, the services on the others) a "remote" client runs on
the scan's CPU, where the FIFO scan preempts it at once, so the services' CPUs hold the
servers' work only; a remote abuser runs there at SCHED_IDLE as well, so that its own CPU
(0.7 s per 2 s encoding 50,000-node Reads) never delays the measuring clients, which would be
on a third machine. A "local" client shares the services' CPUs at normal priority: what a
process on the PLC's own machine costs them. Without a scan CPU of its own, all share.
Does not know: what the clients send, or what the figures mean.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass

from softplc.runtime.realtime import Realtime


@dataclass(frozen=True, slots=True)
class Placement:
    cpus: frozenset[int] | None  # None: as inherited
    idle: bool = False  # SCHED_IDLE: runs only when no normal task wants the CPU

    def words(self) -> str:
        where = "any CPU" if self.cpus is None else f"CPU {', '.join(map(str, sorted(self.cpus)))}"
        return f"{where}{', SCHED_IDLE' if self.idle else ''}"


def _services_cpus(realtime: Realtime) -> frozenset[int] | None:
    """Every CPU of the machine but the scan's (runtime/realtime.py keep_off_scan_cpu)."""
    if realtime.cpu is None:
        return None
    return frozenset(range(os.cpu_count() or 1)) - {realtime.cpu} or None


def clients(realtime: Realtime, remote: bool) -> Placement:
    """The measuring clients: on the scan's CPU (`remote`), or with the services."""
    if remote and realtime.cpu is not None:
        return Placement(frozenset({realtime.cpu}))
    return Placement(_services_cpus(realtime))


def abuser(realtime: Realtime, remote: bool) -> Placement:
    """An abuser: beside the measuring clients below them (`remote`), or with the services
    at normal priority."""
    if remote and realtime.cpu is not None:
        return Placement(frozenset({realtime.cpu}), idle=True)
    return Placement(_services_cpus(realtime))


def place(placement: Placement, pid: int = 0) -> Placement:
    """Apply `placement` to the thread `pid` (0: the caller); threads it starts later inherit
    it. What it runs with now (a refusal leaves it as it was)."""
    with contextlib.suppress(OSError):
        if placement.cpus is not None:
            os.sched_setaffinity(pid, placement.cpus)
        policy = os.SCHED_IDLE if placement.idle else os.SCHED_OTHER
        if os.sched_getscheduler(pid) != policy:
            os.sched_setscheduler(pid, policy, os.sched_param(0))
    try:
        return Placement(frozenset(os.sched_getaffinity(pid)),
                         os.sched_getscheduler(pid) == os.SCHED_IDLE)
    except OSError:
        return Placement(None)
