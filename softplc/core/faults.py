"""Device fault policy: when a silent device faults the PLC, and when the PLC may run again.

Owns: the per-device verdict (starting, ok, holding, fault) from one answering/not-answering
observation per scan, the device events, faulting the PLC before (and after) a scan, and
auto-recovery of device faults. Pure: values in (answers, now_ns), values out (events).
Does not know: drivers, sockets, clocks (docs/faults.md describes the behaviour).
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Protocol

from softplc.core.lifecycle import PlcState
from softplc.core.problems import FaultCode
from softplc.core.symbols import FaultPolicy, OnFailure


class Monitored(Protocol):
    """What the monitor reads of, and does to, the PLC it is given (core/plc.py's Plc is
    one; the scan owns a DeviceMonitor, which does not import it)."""

    @property
    def state(self) -> PlcState: ...
    @property
    def fault_code(self) -> FaultCode: ...
    def fault(self, code: FaultCode, now_ns: int | None = None, reason: str = "") -> None: ...
    def recover(self, now_ns: int) -> bool: ...

FAULT_DEVICE = FaultCode.DEVICE

DEFAULT_POLICY = FaultPolicy()  # for a driver the io image does not declare (tests, tools)


class Verdict(enum.Enum):
    STARTING = "starting"  # opened, not answered yet, within startup_s
    OK = "ok"
    HOLDING = "holding"  # not answering; the last good inputs are still used
    FAULT = "fault"  # not answering beyond the policy: the PLC may not run


@dataclass(slots=True)
class DeviceWatch:
    """One device's record. `failing_scans` counts scans without an answer, in a row."""

    name: str
    opened_ns: int | None = None
    answered: bool = False
    failing_scans: int = 0
    verdict: Verdict = Verdict.STARTING
    reason: str = ""

    def observe(self, answering: bool, policy: FaultPolicy, now_ns: int) -> list[str]:
        """Take one scan's observation; return the device events it causes."""
        if self.opened_ns is None:
            self.opened_ns = now_ns
        before = self.verdict
        if answering:
            if before is Verdict.OK:
                return []  # the steady state: nothing to change, nothing to say
            self.answered, self.failing_scans, self.verdict = True, 0, Verdict.OK
            return [f"device_ok:{self.name}"] if before is not Verdict.STARTING else []
        if not self.answered and now_ns - self.opened_ns < policy.startup_s * 1e9:
            return []  # a device still booting is not a failing one
        self.failing_scans += 1
        held = policy.hold_scans if policy.on_failure is OnFailure.HOLD else 0
        self.verdict = Verdict.HOLDING if self.failing_scans <= held else Verdict.FAULT
        events = [f"device_down:{self.name}"] if self.failing_scans == 1 else []
        if self.verdict is Verdict.FAULT and before is not Verdict.FAULT:
            events.append(f"device_fault:{self.name}")
        return events

    def report(self) -> dict[str, object]:
        return {"verdict": self.verdict.value, "failing_scans": self.failing_scans,
                "reason": self.reason}


class DeviceMonitor:
    """Every driver's watch, and what they mean for the PLC.

    The PLC faults (FAULT_DEVICE, safe outputs) when it is RUNNING and some device's verdict
    is FAULT: checked before the scan, so the program never runs on a failed device's inputs,
    and after it, so a start or resume while a device is failed faults in that same scan.
    A device fault is left only by reset or download (the lifecycle table), or by itself
    when every device that caused it answers again, all of them have auto_recover, and no
    other device is failed.
    """

    def __init__(self) -> None:
        self.watches: dict[str, DeviceWatch] = {}
        self.culprits: set[str] = set()  # devices behind the current device fault
        self.failed: list[str] = []  # devices whose verdict is FAULT, as of the last observation

    def before_scan(self, plc: Monitored, answering: Mapping[str, bool],
                    policies: Mapping[str, FaultPolicy], why: Callable[[str], str],
                    now_ns: int) -> list[str]:
        events: list[str] = []
        observed = False
        for name, ok in answering.items():
            watch = self.watches.get(name) or self.watches.setdefault(name, DeviceWatch(name))
            if ok and watch.verdict is Verdict.OK:
                continue  # the steady state, kept cheap: this runs every scan
            observed = True
            events += watch.observe(ok, policies.get(name, DEFAULT_POLICY), now_ns)
            if not ok and watch.verdict in (Verdict.HOLDING, Verdict.FAULT):
                watch.reason = why(name)
        if observed:
            self.failed = sorted(n for n, w in self.watches.items() if w.verdict is Verdict.FAULT)
        if plc.state is PlcState.FAULTED and plc.fault_code == FAULT_DEVICE:
            events += self._maybe_recover(plc, policies, now_ns)
        else:
            self.culprits.clear()
        return events + self.after_scan(plc, now_ns)

    def after_scan(self, plc: Monitored, now_ns: int) -> list[str]:
        failed = self.failed
        if not failed or plc.state is not PlcState.RUNNING:
            return []
        self.culprits = set(failed)
        plc.fault(FAULT_DEVICE, now_ns, "; ".join(self._describe(n) for n in failed))
        return ["plc_fault:device"]

    def _maybe_recover(self, plc: Monitored, policies: Mapping[str, FaultPolicy],
                       now_ns: int) -> list[str]:
        if self.failed:
            return []
        culprits = self.culprits
        if not culprits or not all(policies.get(n, DEFAULT_POLICY).auto_recover for n in culprits):
            return []
        if not plc.recover(now_ns):
            return []
        self.culprits = set()
        return ["plc_recovered:device"]

    def _describe(self, name: str) -> str:
        watch = self.watches[name]
        return f"device {name} not answering for {watch.failing_scans} scans: {watch.reason}"

    def report(self) -> dict[str, dict[str, object]]:
        return {name: watch.report() for name, watch in sorted(self.watches.items())}

    def forget(self) -> None:
        """New drivers (another io image): no history carries over."""
        self.watches.clear()
        self.culprits.clear()
        self.failed = []
