"""CycleWatchdog, the pure rule that tells a slow host from a stuck scan (docs/faults.md): a
scan over budget counts, `sensitivity` in a row fault, one over the hard limit faults alone;
a stall faults only past its own limit. Values in, reasons out: no clock, no loop."""

from __future__ import annotations

import pytest

from softplc.core.judge import CycleWatchdog

MS = 1_000_000


def rule(sensitivity: int = 3) -> CycleWatchdog:
    return CycleWatchdog(100 * MS, sensitivity, 1500 * MS, 1500 * MS)


def faults(wd: CycleWatchdog, scans_ms: list[int]) -> list[int]:
    """The indexes of the scans (taking these times) after which the rule faults."""
    return [k for k, ms in enumerate(scans_ms) if wd.check(k, ms * MS)]


def test_one_scan_over_budget_does_not_fault_three_in_a_row_do() -> None:
    assert faults(rule(), [5, 106, 5, 5]) == []
    assert faults(rule(), [5, 150, 150, 5, 150, 150, 5]) == []  # two in a row, twice
    assert faults(rule(), [5, 150, 150, 150, 5]) == [3]


def test_the_reason_says_how_many_in_a_row_and_the_budget() -> None:
    wd = rule(2)
    assert wd.check(7, 120 * MS) == ""
    reason = wd.check(8, 130 * MS)
    assert "2 scans in a row over the budget of 100 ms" in reason
    assert "sensitivity 2" in reason and "scan 8 took 130.0 ms" in reason


def test_sensitivity_one_faults_at_the_first_scan_over_budget() -> None:
    assert faults(rule(1), [5, 101, 5]) == [1]


def test_one_scan_over_the_hard_limit_faults_alone() -> None:
    wd = rule()
    assert faults(wd, [5, 1400, 5]) == []
    reason = wd.check(9, 1501 * MS)
    assert reason == "scan 9 took 1501.0 ms (hard limit 1500 ms for one scan)"


def test_a_scan_not_running_or_within_budget_starts_the_count_anew() -> None:
    wd = rule()
    wd.check(0, 150 * MS)
    wd.check(1, 150 * MS)
    assert wd.check(2, 150 * MS, running=False) == "" and wd.over == 0
    assert faults(wd, [150, 150]) == []


def test_an_exempt_scan_neither_counts_nor_resets() -> None:
    wd = rule()
    wd.check(0, 150 * MS)
    wd.check(1, 150 * MS)
    assert wd.check(2, 900 * MS, watched=False) == "" and wd.over == 2
    assert wd.check(3, 150 * MS) != ""


def test_the_hard_limit_is_never_below_the_budget() -> None:
    wd = CycleWatchdog(2000 * MS, 3, 500 * MS)
    assert wd.hard_ns == 2000 * MS
    assert wd.check(0, 1000 * MS) == ""


def test_a_stall_faults_only_past_its_limit_and_not_when_switched_off() -> None:
    wd = rule()
    assert wd.stall(1000 * MS) == ""  # issue 26: a 500 ms gap on a busy host faulted
    assert "cycle started 1500 ms late (stall limit 1500 ms)" in wd.stall(1500 * MS)
    assert CycleWatchdog(100 * MS, 3, 1500 * MS, 0).stall(60_000 * MS) == ""


def test_a_sensitivity_below_one_is_refused() -> None:
    with pytest.raises(ValueError, match="sensitivity 0 must be >= 1"):
        CycleWatchdog(100 * MS, 0, 1500 * MS)
