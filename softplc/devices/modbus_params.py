"""The params of a `kind: modbus` driver, parsed and validated from DriverSpec.params.

Owns: ModbusParams (connection and timing), LinkParams (what the I/O cycle reads of any
Modbus driver's params, TCP or RTU), parse_params (the checks every kind shares) and
Heartbeat (the remote device's own communication watchdog: a counter register the driver
keeps changing, and a timeout register written at every connect). Every bad value is a
DriverConfigError naming the driver, the key and what was expected.
Does not know: sockets, serial lines, threads, the scan.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Protocol, TypeVar

from softplc.core.symbols import DriverSpec
from softplc.core.units import parse_duration_ns
from softplc.devices.driver import DriverConfigError
from softplc.devices.modbus_plan import MAX_OFFSET, IoPlan, Table, WordOrder

HEARTBEAT_MIN_NS = 10_000_000  # 10 ms: faster is noise on the wire, not safety
HEARTBEAT_MAX_NS = 60_000_000_000
_HEARTBEAT_KEYS = ("register", "period", "watchdog_register", "watchdog_value")
WORD_ORDERS = tuple(o.value for o in WordOrder)


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """`register`: the holding register (0-based) that gets a counter 1, 2, ... 65535, 0, 1, ...
    at most once per `period_ns`, in the I/O cycles the scans trigger (so it stops when the
    scans stop). `watchdog_register`/`watchdog_value`: written once per connection, before any
    output, to arm the device's timeout (the value is in the device's own unit)."""

    register: int
    period_ns: int
    watchdog_register: int | None = None
    watchdog_value: int | None = None


class LinkParams(Protocol):
    """What the I/O cycle (modbus_link.py) reads of a Modbus driver's params."""

    @property
    def unit(self) -> int: ...
    @property
    def timeout_s(self) -> float: ...
    @property
    def reconnect_min_s(self) -> float: ...
    @property
    def reconnect_max_s(self) -> float: ...
    @property
    def heartbeat(self) -> Heartbeat | None: ...
    @property
    def word_order(self) -> str: ...


class _Checked(Protocol):
    def _problem(self) -> str | None: ...


P = TypeVar("P", bound=_Checked)


def parse_params(cls: type[P], spec: DriverSpec, plan: IoPlan | None,
                 required: tuple[str, ...]) -> P:
    """`cls` (a dataclass of params) from spec.params: unknown or missing keys, the heartbeat
    and every value checked. Raises DriverConfigError listing the first problem found."""
    known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    unknown = sorted(set(spec.params) - known)
    if unknown:
        raise DriverConfigError(
            f"driver {spec.name!r}: unknown params {unknown}, expected {sorted(known)}"
        )
    missing = [key for key in required if key not in spec.params]
    if missing:
        raise DriverConfigError(f"driver {spec.name!r}: params {' and '.join(required)} "
                                f"{'is' if len(required) == 1 else 'are'} required")
    values = dict(spec.params)
    if "heartbeat" in values:
        values["heartbeat"] = parse_heartbeat(spec.name, values["heartbeat"], plan)
    params = cls(**values)
    problem = params._problem()
    if problem:
        raise DriverConfigError(f"driver {spec.name!r}: {problem}")
    return params


def timing_problem(params: LinkParams, poll: str, units: range = range(256)) -> str | None:
    """The checks of the keys every Modbus kind shares, or None."""
    checks = (
        (_is_int(params.unit) and params.unit in units,
         f"unit must be an integer in {units.start}..{units.stop - 1}"),
        (_positive(params.timeout_s), "timeout_s must be a positive number"),
        (_positive(params.reconnect_min_s), "reconnect_min_s must be a positive number"),
        (
            _positive(params.reconnect_max_s)
            and params.reconnect_max_s >= params.reconnect_min_s,
            "reconnect_max_s must be a number >= reconnect_min_s",
        ),
        (poll == "scan", f"poll {poll!r}: only 'scan' (one cycle per scan) exists"),
        (params.word_order in WORD_ORDERS, f"word_order {params.word_order!r}: expected big "
                                           "(the high word first) or little"),
    )
    return next((msg for ok, msg in checks if not ok), None)


@dataclass(frozen=True, slots=True)
class ModbusParams:
    host: str
    port: int
    unit: int = 1
    timeout_s: float = 0.2
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    poll: str = "scan"
    heartbeat: Heartbeat | None = None
    word_order: str = "big"  # of 32/64-bit values' registers (modbus_plan.WordOrder)

    @classmethod
    def from_spec(cls, spec: DriverSpec, plan: IoPlan | None = None) -> ModbusParams:
        """Raises DriverConfigError (also a ValueError) listing the first problem found."""
        return parse_params(cls, spec, plan, ("host", "port"))

    def _problem(self) -> str | None:
        checks = (
            (isinstance(self.host, str) and bool(self.host), "host must be a non-empty string"),
            (_is_int(self.port) and 1 <= self.port <= 65535, "port must be an integer in 1..65535"),
        )
        return next((msg for ok, msg in checks if not ok), None) or timing_problem(self, self.poll)


def parse_heartbeat(driver: str, value: Any, plan: IoPlan | None) -> Heartbeat:
    """`{register: 40, period: 100ms, watchdog_register: 41, watchdog_value: 500}`."""
    where = f"driver {driver!r}: heartbeat"
    if not isinstance(value, Mapping):
        raise DriverConfigError(f"{where}: expected a mapping {{register: N, period: 100ms}}, "
                                f"got {value!r}")
    unknown = sorted(str(k) for k in set(value) - set(_HEARTBEAT_KEYS))
    if unknown:
        raise DriverConfigError(f"{where}: unknown keys {unknown}, expected "
                                f"{list(_HEARTBEAT_KEYS)}")
    if "register" not in value or "period" not in value:
        raise DriverConfigError(f"{where}: register and period are required")
    register = _register(where, "register", value["register"])
    period_ns = _period_ns(where, value["period"])
    has_reg, has_value = "watchdog_register" in value, "watchdog_value" in value
    if has_reg != has_value:
        raise DriverConfigError(f"{where}: watchdog_register and watchdog_value go together")
    wd_reg = _register(where, "watchdog_register", value["watchdog_register"]) if has_reg else None
    wd_value = _register(where, "watchdog_value", value["watchdog_value"]) if has_value else None
    if wd_reg is not None and wd_reg == register:
        raise DriverConfigError(f"{where}: watchdog_register {wd_reg} is the heartbeat register")
    _check_free(where, plan, {"register": register, "watchdog_register": wd_reg})
    return Heartbeat(register, period_ns, wd_reg, wd_value)


def _register(where: str, key: str, value: Any) -> int:
    if not _is_int(value) or not 0 <= value <= MAX_OFFSET:
        raise DriverConfigError(f"{where}.{key}: expected an integer in 0..{MAX_OFFSET}, "
                                f"got {value!r}")
    return int(value)


def _period_ns(where: str, value: Any) -> int:
    try:
        period_ns = parse_duration_ns(value)
    except ValueError as exc:
        raise DriverConfigError(f"{where}.period: {exc}") from None
    if not HEARTBEAT_MIN_NS <= period_ns <= HEARTBEAT_MAX_NS:
        raise DriverConfigError(f"{where}.period: {value!r} is not within 10ms..60s")
    return period_ns


def _check_free(where: str, plan: IoPlan | None, registers: Mapping[str, int | None]) -> None:
    """The heartbeat registers must not be holding registers the outputs also write."""
    if plan is None:
        return
    for key, register in registers.items():
        for block in plan.writes:
            if register is None or block.table is not Table.HR:
                continue
            if block.start <= register < block.start + block.count:
                raise DriverConfigError(
                    f"{where}.{key}: hr:{register} is already an output channel ({block})"
                )


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _positive(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and value > 0
