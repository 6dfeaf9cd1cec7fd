"""Scan timing statistics over a sliding window: execution time and wake-up lateness.

Owns: TimingStats (O(1) record per scan into numpy ring buffers; summary on demand) and
TimingSummary (the frozen, JSON-friendly result).
Does not know: clocks, the scan loop, what counts as an overrun (the caller says).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Final

import numpy as np
import numpy.typing as npt

# Percentiles follow numpy's method="inverted_cdf": the k-th smallest sample with
# k = ceil(q * n), the smallest x with F(x) >= q. It is an observed sample, never an
# interpolation between two scans, so a reported p99 is a lateness that really happened.
# Computed with one np.partition (about 11 µs for 1000 scans) because np.percentile costs
# about 260 µs per call in numpy 2.4, too much for a status refreshed every scan.
PERCENTILE_METHOD: Final = "inverted_cdf"


@dataclass(frozen=True, slots=True)
class TimingSummary:
    """Figures over the last `window` scans, in microseconds; overruns and scans since start.
    All figures are 0.0 before the first scan."""

    exec_min_us: float
    exec_median_us: float
    exec_p99_us: float
    exec_max_us: float
    lateness_min_us: float
    lateness_median_us: float
    lateness_p99_us: float
    lateness_max_us: float
    overruns: int
    scans: int
    window: int

    def as_dict(self) -> dict[str, float | int]:
        # Flat: one getattr a field (dataclasses.asdict deep-copies each value, a quarter of
        # a status document's cost, and every figure here is a number).
        return {name: getattr(self, name) for name in _FIELDS}


_FIELDS: Final = tuple(f.name for f in fields(TimingSummary))


class TimingStats:
    """Ring buffers of the last `window` execution times and latenesses (ns)."""

    __slots__ = ("_exec", "_late", "_next", "last_exec_ns", "max_exec_ns", "overruns", "scans")

    def __init__(self, window: int = 1000) -> None:
        if window <= 0:
            raise ValueError(f"the statistics window must hold at least one scan, got {window}")
        self._exec = np.zeros(window, dtype=np.int64)
        self._late = np.zeros(window, dtype=np.int64)
        self._next = 0
        self.scans = 0
        self.overruns = 0
        self.last_exec_ns = 0
        self.max_exec_ns = 0  # since start, unlike the windowed exec_max_us

    @property
    def window(self) -> int:
        return len(self._exec)

    def record(self, exec_ns: int, lateness_ns: int, *, overrun: bool = False,
               skipped: int = 0) -> None:
        """One scan: how long it ran, how late it started, whether it missed its period
        (`overrun`), or how many whole slots it ran past (`skipped`, each one an overrun)."""
        i = self._next
        self._exec[i] = exec_ns
        self._late[i] = lateness_ns
        self._next = i + 1 if i + 1 < len(self._exec) else 0
        self.scans += 1
        self.overruns += max(skipped, 1 if overrun else 0)
        self.last_exec_ns = exec_ns
        if exec_ns > self.max_exec_ns:
            self.max_exec_ns = exec_ns

    def reset(self) -> None:
        self._next = self.scans = self.overruns = self.last_exec_ns = self.max_exec_ns = 0

    def summary(self) -> TimingSummary:
        filled = min(self.scans, len(self._exec))
        e_min, e_median, e_p99, e_max = _figures_us(self._exec[:filled])
        l_min, l_median, l_p99, l_max = _figures_us(self._late[:filled])
        return TimingSummary(
            exec_min_us=e_min,
            exec_median_us=e_median,
            exec_p99_us=e_p99,
            exec_max_us=e_max,
            lateness_min_us=l_min,
            lateness_median_us=l_median,
            lateness_p99_us=l_p99,
            lateness_max_us=l_max,
            overruns=self.overruns,
            scans=self.scans,
            window=filled,
        )


def _figures_us(samples_ns: npt.NDArray[np.int64]) -> tuple[float, float, float, float]:
    """min, median, p99, max in µs; the window's order does not matter for any of them."""
    n = samples_ns.size
    if n == 0:
        return (0.0, 0.0, 0.0, 0.0)
    ranks = [0, _rank(50, n), _rank(99, n), n - 1]
    ordered = np.partition(samples_ns, ranks)
    lo, median, p99, hi = (float(ordered[r]) / 1000.0 for r in ranks)
    return (lo, median, p99, hi)


def _rank(percent: int, n: int) -> int:
    """0-based index of the inverted-CDF percentile in sorted order: ceil(percent * n / 100) - 1."""
    return max(0, -(-percent * n // 100) - 1)
