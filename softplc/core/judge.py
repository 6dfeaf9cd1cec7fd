"""The runtime's measurements, judged by the PLC (docs/design.md section 8).

Owns: Observed (device answers and why the silent ones are silent, a watchdog overrun, a
stall) and judge(): watchdog and stall faults, and the device fault policy through the
PLC's DeviceMonitor, kept cheap while every device keeps answering.
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
