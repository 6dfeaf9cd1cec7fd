"""Durations with units, as programs, command lines, device parameters and simulation scripts
write them: plain (10ms, 2s, 1.5s, 500us, 1min) or as IEC 61131-3 time literals (T#5s,
TIME#1m30s, T#1h_2m_3s_500ms, LT#1.5s).

Owns: parse_duration_ns, the one reader of both forms. Does not know: where the text came from.
"""

from __future__ import annotations

import re
from decimal import Decimal, InvalidOperation

# Units are read case-insensitively (10MS as IEC 61131-3's T#10MS writes it); micro as "u",
# the micro sign (U+00B5) or the Greek mu (U+03BC), which keyboards give interchangeably.
_UNITS = {"ns": 1, "us": 1_000, "µs": 1_000, "μs": 1_000, "ms": 1_000_000,
          "s": 1_000_000_000, "min": 60_000_000_000, "h": 3_600_000_000_000}
_DURATION = re.compile(r"\s*(\d+(?:\.\d*)?|\.\d+)\s*(ns|us|µs|μs|ms|s|min|h)\s*",
                       re.IGNORECASE)
_SPELLED = ", ".join(u for u in _UNITS if u not in ("µs", "μs"))

_IEC = re.compile(r"\s*(?:T|TIME|LT|LTIME)#(-?)(.*?)\s*", re.IGNORECASE)
# Largest unit first, each at most once (IEC 61131-3 table 8): d h m s ms us ns.
_PARTS = re.compile(r"(?:(\d+(?:\.\d+)?)d)?(?:(\d+(?:\.\d+)?)h)?(?:(\d+(?:\.\d+)?)m(?!s))?"
                    r"(?:(\d+(?:\.\d+)?)s)?(?:(\d+(?:\.\d+)?)ms)?(?:(\d+(?:\.\d+)?)us)?"
                    r"(?:(\d+(?:\.\d+)?)ns)?", re.IGNORECASE)
_IEC_NS = (86_400 * 10**9, 3_600 * 10**9, 60 * 10**9, 10**9, 10**6, 10**3, 1)


def parse_duration_ns(text: str | int) -> int:
    """`"10ms"` or `"T#10ms"` -> 10_000_000. A bare 0 is accepted; any other number needs a
    unit. ValueError (one message, what to write) otherwise."""
    if isinstance(text, int) and not isinstance(text, bool) and text == 0:
        return 0
    if isinstance(text, str) and _IEC.fullmatch(text) is not None:
        return _iec_ns(text)
    m = _DURATION.fullmatch(str(text))
    if m is None:
        raise ValueError(f"bad duration {text!r}: expected a number with a unit ({_SPELLED}), "
                         "e.g. 10ms or 2s")
    try:
        value = Decimal(m.group(1)) * _UNITS[m.group(2).lower()]
    except InvalidOperation:
        raise ValueError(f"bad duration {text!r}") from None
    return _whole(value, text)


def _iec_ns(text: str) -> int:
    """`T#1m30s` -> 90_000_000_000."""
    head = _IEC.fullmatch(text)
    body = head.group(2).replace("_", "") if head else ""
    parts = _PARTS.fullmatch(body) if head and not head.group(1) else None
    if parts is None or not body:
        raise ValueError(f"bad duration {text!r}: an IEC time is T# and units from days to "
                         "nanoseconds, largest first, e.g. T#5s, T#1m30s, T#1h_2m, T#250ms; "
                         "or write 5s, 90s, 250ms")
    return _whole(sum((Decimal(v) * unit for v, unit in zip(parts.groups(), _IEC_NS,
                                                              strict=True) if v), Decimal(0)),
                  text)


def _whole(value: Decimal, text: str | int) -> int:
    if value != value.to_integral_value():
        raise ValueError(f"bad duration {text!r}: finer than a nanosecond")
    return int(value)
