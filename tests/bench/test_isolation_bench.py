"""Where the isolation bench's clients run (softplc/bench/placement.py, BENCHMARKS.md,
Isolation): remote pollers on the scan's CPU, remote abusers there too below them
(SCHED_IDLE), local ones on the services' CPUs, and on a machine without a scan CPU of its
own, where they were. Real processes, never timed."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator

import pytest

from softplc.bench import placement
from softplc.bench.isolationbench import ABUSES, LOCAL, RUNS
from softplc.runtime.realtime import NORMAL, Realtime


@pytest.fixture
def child() -> Iterator[int]:
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        yield proc.pid
    finally:
        proc.kill()
        proc.wait(10)


def test_remote_clients_run_on_the_scan_cpu_the_abuser_below_them(child: int) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        pytest.skip("one CPU: there is no scan CPU of its own")
    scan = Realtime(cpu=cpus[-1])
    services = frozenset(range(os.cpu_count() or 1)) - {cpus[-1]}
    got = placement.place(placement.abuser(scan, remote=True), child)
    assert got == placement.Placement(frozenset({cpus[-1]}), idle=True)
    assert "SCHED_IDLE" in got.words()
    assert placement.place(placement.abuser(scan, remote=False), child) == \
        placement.Placement(services)  # back to normal priority, with the services
    assert placement.place(placement.clients(scan, remote=True), child) == \
        placement.Placement(frozenset({cpus[-1]}))
    assert placement.place(placement.clients(scan, remote=False), child) == \
        placement.Placement(services)


def test_without_a_scan_cpu_every_client_stays_where_it_was(child: int) -> None:
    before = frozenset(os.sched_getaffinity(child))
    assert placement.abuser(NORMAL, remote=True) == placement.Placement(None)
    assert placement.place(placement.clients(NORMAL, remote=True), child).cpus == before


def test_every_abuse_runs_with_remote_clients_and_two_again_with_local_ones() -> None:
    assert [(name, kind) for name, kind, remote in RUNS if remote] == [(k, k) for k in ABUSES]
    assert [name for name, _, remote in RUNS if not remote] == [f"{k}_local" for k in LOCAL]
