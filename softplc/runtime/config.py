"""The scan process's configuration: what `softplc run` and the benchmarks hand the loop.

Owns: LoopConfig, a frozen value (it crosses into the scan process by pickling).
Does not know: how any of it is used (runtime/loop.py, runtime/prepare.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from softplc.core.image import ImageSizes
from softplc.runtime.realtime import NORMAL, Realtime


@dataclass(frozen=True, slots=True)
class LoopConfig:
    program: str | None = None  # compiled and downloaded on the first scan
    start: bool = False
    period_ns: int = 10_000_000
    plant: str | None = None  # overrides the plant of a sim driver
    seed: int = 0
    trace: str | None = None
    # The watchdog (docs/faults.md): a scan longer than period x watchdog is over budget;
    # watchdog_sensitivity of them in a row fault, and so does one scan (or one that has not
    # ended) longer than watchdog_hard_ns. On 2 cores at load 10-20 an idle 10 ms PLC had
    # scans of up to 105 ms and a cycle that started 1047 ms late in runs of 3-15 min (issue 26
    # saw a 106 ms scan and a cycle over 500 ms late at load 2-5): the hard limit is about
    # three times the longest gap seen (docs/faults.md, watchdog).
    watchdog: float = 10.0
    watchdog_sensitivity: int = 3
    watchdog_hard_ns: int = 3_000_000_000
    root: str | None = None  # downloads may only reference files under this directory
    programs_dir: str | None = None  # a plain-text download's home (None: root/programs)
    sizes: ImageSizes = field(default_factory=ImageSizes)
    max_scans: int | None = None  # stop after this many (tests, benchmarks)
    state_dir: str | None = None  # retain snapshots live here; None: no retain, always cold
    retain_interval_ns: int = 1_000_000_000  # 0: only on stop
    warm_start: str = "run"  # a warm restart of a RUNNING snapshot: "run" resumes, "stop" waits
    # What a start of the scan process that is not the supervisor's restart of a crashed one
    # does (docs/retain.md, boot policy): "stop", "warm" or "cold". `softplc run` resolves the
    # installation's (default "stop"); a loop built directly gets today's warm restart.
    boot_policy: str = "warm"
    boot_policy_source: str = ""  # where softplc run took it from, for status
    realtime: Realtime = NORMAL  # SCHED_FIFO priority and CPU of the scan process
    on_stall: str = "fault"  # a stall long enough to fault (below): "fault" or "continue"
    # A cycle that starts period x watchdog late is a stall: counted, an event. It faults (with
    # on_stall "fault") once it is also this long: a general-purpose OS delays a sleeping
    # process by tens, under heavy load hundreds of ms (the figures above), which lateness and
    # overruns already show; a pause of seconds (SIGSTOP, VM pause, swap storm) is no hiccup.
    stall_fault_ns: int = 3_000_000_000
    restarts: int = 0  # how often the supervisor restarted the scan process before this one
    restart_reason: str = ""  # why it restarted it last
    first_event_seq: int = 0  # event numbers go on after this one (a restart: the dead one's)
    # The dead scan process was paused at a breakpoint (or stepping): what the pause was.
    # Not empty: the restart does not run on; the PLC waits STOPPED, outputs safe, the net
    # as it was paused (docs/debug.md, a pause and a restart).
    paused_at_restart: str = ""
    boot: bool = True  # no program given: run the boot program of state_dir, if any
    verify: str = "warn"  # analysis gate on downloads: "refuse", "warn" or "off"
    # `program` compiled once by `softplc run` (runtime/compileproc.py StartProgram): what a
    # start and every restart load instead of compiling (None: the scan process compiles it).
    compiled: Any = None
