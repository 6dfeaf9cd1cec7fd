"""Sliding-window timing statistics against numpy on known data."""

from __future__ import annotations

import numpy as np
import pytest

from softplc.runtime.stats import PERCENTILE_METHOD, TimingStats, TimingSummary


def _expected(samples: np.ndarray) -> tuple[float, float, float, float]:
    median, p99 = np.percentile(samples, (50, 99), method=PERCENTILE_METHOD)
    return (
        float(samples.min()) / 1000,
        float(median) / 1000,
        float(p99) / 1000,
        float(samples.max()) / 1000,
    )


def test_empty_summary_is_all_zero() -> None:
    summary = TimingStats().summary()
    assert summary == TimingSummary(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0)


def test_known_data() -> None:
    stats = TimingStats(window=100)
    for i in range(1, 101):  # exec 1..100 µs, lateness 2..200 µs
        stats.record(i * 1000, 2 * i * 1000, overrun=(i % 10 == 0))
    s = stats.summary()
    assert (s.exec_min_us, s.exec_median_us, s.exec_p99_us, s.exec_max_us) == (1, 50, 99, 100)
    assert (s.lateness_min_us, s.lateness_median_us, s.lateness_p99_us) == (2, 100, 198)
    assert s.lateness_max_us == 200
    assert (s.overruns, s.scans, s.window) == (10, 100, 100)


@pytest.mark.parametrize("count", [1, 2, 3, 7, 99, 100, 101, 999, 1000, 1001, 2500])
def test_percentiles_match_numpy(count: int) -> None:
    rng = np.random.default_rng(count)
    execs = rng.integers(0, 5_000_000, count)
    lates = rng.integers(0, 200_000, count)
    stats = TimingStats(window=1000)
    for e, late in zip(execs, lates, strict=True):
        stats.record(int(e), int(late))
    s = stats.summary()
    assert (s.exec_min_us, s.exec_median_us, s.exec_p99_us, s.exec_max_us) == _expected(
        execs[-1000:]
    )
    assert (
        s.lateness_min_us,
        s.lateness_median_us,
        s.lateness_p99_us,
        s.lateness_max_us,
    ) == _expected(lates[-1000:])
    assert (s.scans, s.window) == (count, min(count, 1000))


def test_window_slides_but_totals_do_not() -> None:
    stats = TimingStats(window=10)
    for _ in range(10):
        stats.record(1_000_000, 0, overrun=True)  # an early slow patch
    for _ in range(10):
        stats.record(5_000, 1_000)
    s = stats.summary()
    assert s.exec_max_us == 5.0  # the slow scans left the window
    assert s.overruns == 10 and s.scans == 20 and s.window == 10
    assert stats.max_exec_ns == 1_000_000  # since start
    assert stats.last_exec_ns == 5_000


def test_reset_and_as_dict() -> None:
    stats = TimingStats(window=5)
    stats.record(10_000, 1_000, overrun=True)
    stats.reset()
    assert stats.summary().scans == 0
    stats.record(3_000, 500)
    d = stats.summary().as_dict()
    assert d["exec_median_us"] == 3.0 and d["lateness_max_us"] == 0.5
    assert d["overruns"] == 0 and d["scans"] == 1 and d["window"] == 1
    assert set(d) == set(TimingSummary.__dataclass_fields__)


def test_window_must_be_positive() -> None:
    with pytest.raises(ValueError, match="at least one scan"):
        TimingStats(window=0)
