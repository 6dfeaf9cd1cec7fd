"""The invariants the whole-system test checks after every step, against the model.

Owns: `agree` (HTTP status, the Modbus status block and OPC UA say the model's state and
program; the scan count never goes back; forces and HMI memory as the model has them; the
module's outputs safe whenever the PLC is not RUNNING and the program's own outputs when it
is; the net never saw an input no device delivered) and `Violation`, the one failure.
Does not know: how the steps are chosen.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, TypeVar

from softplc.api.client import ApiError, ApiUnreachable
from tests.system import probe
from tests.system.model import FAULTED, RUNNING, Model
from tests.system.programs import ALARM, LAMP, LAMP2, Library, Module
from tests.system.rig import SAFE_WITHIN_S, Run

T = TypeVar("T")
SETTLE_S = 6.0  # a device loss is noticed in one driver cycle (0.5 s timeout) plus start-up


class Violation(AssertionError):
    """An invariant did not hold; the message says which and what was seen."""


def settle(probe_fn: Callable[[], T], ok: Callable[[T], bool], what: str,
           timeout_s: float = SETTLE_S, step_s: float = 0.05) -> T:
    """The first observation `ok` accepts within `timeout_s`, else Violation(what, last)."""
    deadline = time.monotonic() + timeout_s
    last: Any = None
    while True:
        try:
            seen = probe_fn()
        except (ApiError, ApiUnreachable, OSError, ConnectionError, TimeoutError) as exc:
            last = exc
        else:
            if ok(seen):
                return seen
            last = seen
        if time.monotonic() > deadline:
            raise Violation(f"{what}: not within {timeout_s} s; last seen: {_short(last)}")
        time.sleep(step_s)


def agree(run: Run, model: Model, library: Library, module: Module) -> dict[str, Any]:
    """Every view of the PLC agrees with the model (after what just happened settled)."""
    status = _status(run, model, library)
    run.remember(status)
    _block(run, model, library)
    _opcua(run, model)
    _memory(run, model)
    if model.device_up:
        _outputs(run, model, module)
    return status


def _status(run: Run, model: Model, library: Library) -> dict[str, Any]:
    want_hash = library.hashes.get(model.program or "")

    def ok(s: dict[str, Any]) -> bool:  # forces show at the board's next refresh (50 ms)
        return (s.get("state") == model.state and not s.get("stale")
                and s.get("program_hash") == want_hash and _forces(s) == model.forced)

    status = settle(run.api.status, ok, f"status says {model.state}, program "
                    f"{model.program} ({(want_hash or '-')[:12]}), forces {model.forced}")
    scans = int(status["scan_count"])
    if scans < model.scan_floor:
        raise Violation(f"scan count went back: {scans} after {model.scan_floor} was seen")
    model.scan_floor = scans
    if "blind" in (status.get("marking") or {}):
        raise Violation("the net fired saw_low: it acted on `go` low, a value the module "
                        f"never delivered (marking {status.get('marking')})")
    if model.state != FAULTED and status.get("fault_code"):
        raise Violation(f"fault_code {status.get('fault_code')} in state {model.state}")
    return status


def _block(run: Run, model: Model, library: Library) -> None:
    want = library.hashes.get(model.program or "")
    want64 = int(want[:16], 16) if want else 0
    seen = settle(lambda: probe.block(run), lambda b: b.state == model.state and not b.stale
                  and b.forced == len(model.forced),
                  f"Modbus status block says {model.state}, {len(model.forced)} forced")
    if seen.hash64 != want64:
        raise Violation(f"status block program hash {seen.hash64:016x}, want {want64:016x}")
    if seen.scan_count < model.scan_floor:
        raise Violation(f"status block scan count {seen.scan_count} < {model.scan_floor} seen")
    model.scan_floor = max(model.scan_floor, seen.scan_count)
    if (seen.fault_code != 0) != (model.state == FAULTED):
        raise Violation(f"status block fault code {seen.fault_code} in {model.state}")


def _opcua(run: Run, model: Model) -> None:
    if run.opcua is None:
        return
    allowed = model.opcua_states()
    settle(lambda: probe.opcua_state(run), lambda s: s[0] == model.state and s[1] in allowed,
           f"OPC UA says {model.state} / one of {sorted(allowed)}", step_s=0.2)


def _memory(run: Run, model: Model) -> None:
    bit, word = probe.memory(run)
    if model.cmd is not None and bit != model.cmd:
        raise Violation(f"HMI bit %MX0.0 reads {bit}, the model has {model.cmd}")
    if model.word is not None and word != model.word:
        raise Violation(f"HMI word %MW0 reads {word}, the model has {model.word}")


def _outputs(run: Run, model: Model, module: Module) -> None:
    if model.state != RUNNING:
        settle(lambda: probe.coils(module), lambda c: not any(c),
               f"outputs safe (all coils 0) in {model.state}", timeout_s=SAFE_WITHIN_S,
               step_s=0.01)
        return
    bit, _ = probe.memory(run)
    lamp2 = bool(model.forced["lamp2"]) if "lamp2" in model.forced else bit
    want = {LAMP: True, LAMP2: lamp2, ALARM: False}
    settle(lambda: probe.coils(module), lambda c: all(c[k] == v for k, v in want.items()),
           f"RUNNING: the module's coils {want} (lamp on, lamp2 = forced or %MX0.0, alarm off)")


def _forces(status: dict[str, Any]) -> dict[str, int]:
    return {k: int(v) for k, v in (status.get("forced") or {}).items()}


def _short(value: Any) -> str:
    if isinstance(value, dict):
        keep = ("state", "program", "program_hash", "scan_count", "stale", "fault_code",
                "fault_reason", "forced", "marking", "restarts", "devices", "health")
        value = {k: value.get(k) for k in keep if k in value}
    return repr(value)[:600]
