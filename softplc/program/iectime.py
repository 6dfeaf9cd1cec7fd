"""IEC 61131-3 time literals where a program expects a duration: `T#5s`, `TIME#1m30s`,
`T#1h_2m_3s_500ms`, `LT#1.5s`.

Owns: reading them into nanoseconds, and `duration_ns`, a program's delay:/duration: in
either form (the plain one, `5s`, `1.5min`, is core/units.py's).
"""

from __future__ import annotations

import re
from decimal import Decimal

from softplc.core.units import parse_duration_ns

# A delay:/duration: whose text was bad: its problem is reported, and the compiler's checks of
# a missing duration (outputs: held while it runs) must not report the same mistake again.
BAD_DURATION = -1

_PREFIX = re.compile(r"\s*(?:T|TIME|LT|LTIME)#(-?)(.*?)\s*", re.IGNORECASE)
# Largest unit first, each at most once (IEC 61131-3 table 8): d h m s ms us ns.
_PARTS = re.compile(r"(?:(\d+(?:\.\d+)?)d)?(?:(\d+(?:\.\d+)?)h)?(?:(\d+(?:\.\d+)?)m(?!s))?"
                    r"(?:(\d+(?:\.\d+)?)s)?(?:(\d+(?:\.\d+)?)ms)?(?:(\d+(?:\.\d+)?)us)?"
                    r"(?:(\d+(?:\.\d+)?)ns)?", re.IGNORECASE)
_NS = (86_400 * 10**9, 3_600 * 10**9, 60 * 10**9, 10**9, 10**6, 10**3, 1)


def duration_ns(text: str | int) -> int:
    """A program's duration, `T#1m30s` or `90s`. ValueError with what to write."""
    if isinstance(text, str) and _PREFIX.fullmatch(text) is not None:
        return iec_time_ns(text)
    return parse_duration_ns(text)


def iec_time_ns(text: str) -> int:
    """`T#1m30s` -> 90_000_000_000. ValueError (one message, what to write) otherwise."""
    head = _PREFIX.fullmatch(text)
    body = head.group(2).replace("_", "") if head else ""
    parts = _PARTS.fullmatch(body) if head and not head.group(1) else None
    if parts is None or not body:
        raise ValueError(f"bad duration {text!r}: an IEC time is T# and units from days to "
                         "nanoseconds, largest first, e.g. T#5s, T#1m30s, T#1h_2m, T#250ms; "
                         "or write 5s, 90s, 250ms")
    total = sum((Decimal(v) * unit for v, unit in zip(parts.groups(), _NS, strict=True) if v),
                Decimal(0))
    if total != total.to_integral_value():
        raise ValueError(f"bad duration {text!r}: finer than a nanosecond")
    return int(total)
