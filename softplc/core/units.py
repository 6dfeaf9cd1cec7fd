"""Durations with units, as programs and command lines write them (10ms, 2s, 1.5s, 500us, 1min).

Owns: parse_duration_ns. Does not know: where the text came from.
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


def parse_duration_ns(text: str | int) -> int:
    """`"10ms"` -> 10_000_000. A bare 0 is accepted; any other number needs a unit."""
    if isinstance(text, int) and not isinstance(text, bool) and text == 0:
        return 0
    m = _DURATION.fullmatch(str(text))
    if m is None:
        raise ValueError(f"bad duration {text!r}: expected a number with a unit ({_SPELLED}), "
                         "e.g. 10ms or 2s")
    try:
        value = Decimal(m.group(1)) * _UNITS[m.group(2).lower()]
    except InvalidOperation:
        raise ValueError(f"bad duration {text!r}") from None
    if value != value.to_integral_value():
        raise ValueError(f"bad duration {text!r}: finer than a nanosecond")
    return int(value)
