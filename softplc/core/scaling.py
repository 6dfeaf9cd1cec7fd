"""Linear scaling of a symbol between the raw value a device moves and engineering units.

Owns: Scaling (the raw span, the engineering span, the unit, clamping) and its two directions,
`to_eng` (what a program reads) and `to_raw` (what a program's write stores).
Does not know: YAML (program/io_image.py parses `scale:`), the image, drivers, displays.

Rules (docs/programs.md, scaling): the map is the straight line through (raw[0], eng[0]) and
(raw[1], eng[1]), computed in IEEE 754 doubles, exact at both ends. With `clamp` a read is
limited to the engineering span and a write to it (so the raw value stays in the raw span);
without, both directions extrapolate and only the raw type's range limits a write. A raw value
of an integer type is rounded to the nearest, ties to even, as every conversion of the
language (core/datatypes.py `convert`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from softplc.core.datatypes import TypeRangeError

Number = int | float


def _lerp(a: float, b: float, t: float) -> float:
    """a at t=0, b at t=1, exactly at both ends (numpy's lerp rule: from the nearer end)."""
    return a + t * (b - a) if t < 0.5 else b - (1.0 - t) * (b - a)


@dataclass(frozen=True, slots=True)
class Scaling:
    """raw[0] <-> eng[0], raw[1] <-> eng[1]; spans may run backwards (raw 0 = 100 %)."""

    raw: tuple[Number, Number]
    eng: tuple[float, float]
    unit: str = ""
    clamp: bool = False
    whole: bool = True  # the raw type is an integer type: to_raw rounds
    # What the Modbus slave serves (docs/modbus.md, scaled symbols): "raw", the image's
    # value, or "eng", the engineering value in the symbol's type. A display choice, as `unit`.
    modbus: str = "raw"

    def __post_init__(self) -> None:
        if self.raw[0] == self.raw[1] or self.eng[0] == self.eng[1]:
            raise ValueError("a scale's raw and engineering spans must not be empty")

    def to_eng(self, raw: Number) -> float:
        """The engineering value of `raw` (a NaN raw real stays NaN)."""
        (r0, r1), (e0, e1) = self.raw, self.eng
        eng = _lerp(e0, e1, (raw - r0) / (r1 - r0))
        if self.clamp:
            eng = min(max(eng, min(e0, e1)), max(e0, e1))
        return eng

    def to_raw(self, eng: object) -> Number:
        """The raw value a write of `eng` stores, before its type's check (datatypes.stored).
        TypeError for text, TypeRangeError for NaN or an infinity."""
        if isinstance(eng, str) or not isinstance(eng, int | float):
            raise TypeError(f"{type(eng).__name__} cannot be written to a scaled symbol")
        value = float(eng)
        if not math.isfinite(value):
            raise TypeRangeError(f"the result is {'NaN' if math.isnan(value) else 'infinite'}")
        (r0, r1), (e0, e1) = self.raw, self.eng
        if self.clamp:
            value = min(max(value, min(e0, e1)), max(e0, e1))
        raw = _lerp(float(r0), float(r1), (value - e0) / (e1 - e0))
        if not math.isfinite(raw):
            raise TypeRangeError(f"{eng!r} scales to an infinite raw value")
        return round(raw) if self.whole else raw

    def as_dict(self) -> dict[str, Any]:
        """For the status board and displays: `{raw: [..], eng: [..], unit, clamp}`, and
        `modbus: eng` when the Modbus slave serves the engineering value."""
        shown = {"raw": list(self.raw), "eng": list(self.eng), "unit": self.unit,
                 "clamp": self.clamp}
        return shown if self.modbus == "raw" else {**shown, "modbus": self.modbus}
