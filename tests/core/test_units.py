"""The one duration parser (core/units.py): programs, command lines, device parameters and
simulation scripts all read durations with it."""

from __future__ import annotations

import pytest

from softplc.core.units import parse_duration_ns


@pytest.mark.parametrize(
    ("text", "ns"),
    [
        ("10ms", 10_000_000),
        ("1s", 1_000_000_000),
        ("500us", 500_000),
        ("500µs", 500_000),
        ("500μs", 500_000),
        ("2.5s", 2_500_000_000),
        ("3600s", 3_600_000_000_000),
        ("1min", 60_000_000_000),
        ("1.5min", 90_000_000_000),
        ("2h", 7_200_000_000_000),
        ("750ns", 750),
        (" 10 ms ", 10_000_000),
        ("0.1s", 100_000_000),
        (".5ms", 500_000),
        ("0s", 0),
        ("10MS", 10_000_000),
    ],
)
def test_parse_duration(text: str, ns: int) -> None:
    assert parse_duration_ns(text) == ns


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("10", "expected a number with a unit"),
        ("ms", "expected a number with a unit"),
        ("", "expected a number with a unit"),
        ("-5ms", "expected a number with a unit"),
        ("1e3ms", "expected a number with a unit"),
        ("10 m s", "expected a number with a unit"),
        ("10sec", "expected a number with a unit"),
        ("3days", "expected a number with a unit"),
        ("1.5ns", "finer than a nanosecond"),
    ],
)
def test_parse_duration_errors(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message) as err:
        parse_duration_ns(text)
    assert repr(text) in str(err.value)


def test_a_bare_zero_needs_no_unit_but_no_other_number_goes_without() -> None:
    assert parse_duration_ns(0) == 0
    with pytest.raises(ValueError, match="expected a number with a unit"):
        parse_duration_ns(5)  # type: ignore[arg-type]
