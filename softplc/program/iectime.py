"""A program's delay:/duration: values: `T#5s`, `TIME#1m30s`, `5s`, `1.5min`, read by the one
duration parser (core/units.py, which also reads command lines and simulation scripts).

Owns: BAD_DURATION, the mark of a duration whose problem was already reported.
"""

from __future__ import annotations

from softplc.core.units import parse_duration_ns

# A delay:/duration: whose text was bad: its problem is reported, and the compiler's checks of
# a missing duration (outputs: held while it runs) must not report the same mistake again.
BAD_DURATION = -1


def duration_ns(text: str | int) -> int:
    """A program's duration, `T#1m30s` or `90s`. ValueError with what to write."""
    return parse_duration_ns(text)
