"""The runtime's measurements, judged by the PLC (docs/design.md section 8).

Owns: Observed (device answers and why the silent ones are silent, a watchdog overrun, a
stall) and judge(): watchdog and stall faults, and the device fault policy through the
PLC's DeviceMonitor, kept cheap while every device keeps answering; CycleWatchdog, the rule
that tells a slow host from a stuck scan (sensitivity and hard limit, docs/faults.md).
Does not know: how the runtime measures (runtime/runner.py, runtime/loop.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from softplc.core.faults import Verdict
from softplc.core.lifecycle import PlcState
from softplc.core.plc import FAULT_DEVICE, Plc
from softplc.core.problems import FaultCode


@dataclass(frozen=True, slots=True)
class Observed:
    """What the runtime measured for this scan, for the PLC to judge (the scan decides, so a
    trace holding these replays every fault): each device's answer (name -> answering) and
    why the silent ones are silent; a watchdog overrun of the previous scan or a stall of the
    cycle, as the reason text ("" when none)."""

    answering: Mapping[str, bool] = field(default_factory=dict)
    why: Mapping[str, str] = field(default_factory=dict)
    overrun: str = ""
    stall: str = ""


NOTHING_OBSERVED = Observed()


@dataclass(slots=True)
class CycleWatchdog:
    """When scan execution times fault the PLC, as a CODESYS task watchdog with its
    sensitivity: a scan longer than `budget_ns` is over budget, `sensitivity` of them in a row
    fault, and one scan longer than `hard_ns` faults alone. A busy host stretches a scan now
    and then (scans of 105 ms, cycles 1 s late: 2 cores at load 10-20, docs/faults.md); a stuck
    driver or a runaway net stretches every scan, or one without end. Pure: the runtime measures."""

    budget_ns: int
    sensitivity: int
    hard_ns: int
    stall_fault_ns: int = 0  # a cycle that starts this late (and over budget) faults; 0: never
    over: int = 0  # watched scans over budget, in a row

    def __post_init__(self) -> None:
        if self.sensitivity < 1 or self.budget_ns <= 0:
            raise ValueError(f"watchdog: sensitivity {self.sensitivity} must be >= 1 and "
                             f"budget {self.budget_ns} ns above 0")
        self.hard_ns = max(self.hard_ns, self.budget_ns)  # never below the budget itself

    def check(self, scan: int, exec_ns: int, running: bool = True, watched: bool = True) -> str:
        """After scan number `scan`, which took `exec_ns`: why it faults, or "". Only the scans
        of a RUNNING PLC are watched (any other starts the count anew); an exempt one
        (`watched` False: it handled program commands) neither counts nor resets it."""
        if not running or exec_ns <= self.budget_ns:
            self.over = 0
            return ""
        if not watched:
            return ""
        self.over += 1
        took = f"scan {scan} took {exec_ns / 1e6:.1f} ms"
        if exec_ns > self.hard_ns:
            return f"{took} (hard limit {self.hard_ns / 1e6:g} ms for one scan)"
        if self.over >= self.sensitivity:
            return (f"{self.over} scans in a row over the budget of {self.budget_ns / 1e6:g} ms "
                    f"(period x watchdog, sensitivity {self.sensitivity}); {took}")
        return ""

    def hung(self, scan: int, elapsed_ns: int) -> str:
        """Why scan number `scan`, still running after `elapsed_ns`, faults."""
        return (f"scan {scan} has not ended after {elapsed_ns / 1e6:.0f} ms (hard limit "
                f"{self.hard_ns / 1e6:g} ms for one scan)")

    def stall(self, late_ns: int) -> str:
        """Why a cycle that started `late_ns` late faults, or "" (a stall too short to fault,
        or stalls configured not to). A stall is one gap, not a pattern: no sensitivity."""
        if not self.stall_fault_ns or late_ns < max(self.stall_fault_ns, self.budget_ns):
            return ""
        return (f"cycle started {late_ns / 1e6:.0f} ms late (stall limit "
                f"{max(self.stall_fault_ns, self.budget_ns) / 1e6:g} ms): inputs and outputs "
                "were frozen meanwhile")


def judge(plc: Plc, observed: Observed, now_ns: int) -> list[str]:
    """The runtime's measurements, judged before the scan's commands and program. The
    runtime also calls it between scans for a watchdog overrun, so safe outputs go out at
    once; the trace then carries the observation with the next scan."""
    if not observed.overrun and not observed.stall:
        if not observed.answering or _quiet(plc, observed.answering):
            return []  # the steady scan: nothing measured, or every device as it was
        return _judge_devices(plc, observed, now_ns)
    events: list[str] = []
    for code, reason in ((FaultCode.WATCHDOG, observed.overrun),
                         (FaultCode.STALL, observed.stall)):
        if reason and plc.state is PlcState.RUNNING:
            plc.fault(code, None, reason)
            events.append(f"plc_fault:{code.name.lower()}")
    if observed.answering:
        events += _judge_devices(plc, observed, now_ns)
    return events


def _judge_devices(plc: Plc, observed: Observed, now_ns: int) -> list[str]:
    devices = plc.devices
    events = devices.before_scan(plc, observed.answering, plc.policies(),
                                 lambda name: observed.why.get(name, "not answering"), now_ns)
    # The same answers again next scan change nothing (DeviceMonitor.before_scan would only
    # look at every device to find it answering), as long as every watch stays OK.
    steady = (not events and all(observed.answering.values())
              and len(devices.watches) == len(observed.answering)
              and all(w.verdict is Verdict.OK for w in devices.watches.values()))
    plc.steady_answers = observed.answering if steady else None
    return events


def _quiet(plc: Plc, answering: Mapping[str, bool]) -> bool:
    """`answering` is the mapping last judged steady, and the device monitor has nothing to
    do: no failed device, no device fault to recover from, no culprits to clear."""
    devices = plc.devices
    return (answering is plc.steady_answers and not devices.failed and not devices.culprits
            and len(devices.watches) == len(answering)
            and (plc.state is not PlcState.FAULTED or plc.fault_code != FAULT_DEVICE))
