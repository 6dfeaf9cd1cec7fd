"""What every benchmark section shares: tail figures of a sample set, and the progress line.

Owns: percentile figures (inverted-CDF ranks, as runtime/stats.py, so a reported p99 is a
sample that really happened) and a one-line progress display on stderr.
Does not know: what is being measured.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class Figures:
    """Tail figures of one sample set, in the unit the samples were given in."""

    n: int
    min: float
    median: float
    p99: float
    p999: float
    max: float
    mean: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def figures(samples: Iterable[float]) -> Figures:
    values = np.sort(np.asarray(list(samples) if not isinstance(samples, np.ndarray)
                                else samples, dtype=np.float64))
    n = int(values.size)
    if n == 0:
        return Figures(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    def rank(q: float) -> float:  # ceil(q * n) - 1: the smallest x with F(x) >= q
        return float(values[max(0, int(np.ceil(q * n)) - 1)])

    return Figures(n, float(values[0]), rank(0.5), rank(0.99), rank(0.999), float(values[-1]),
                   float(values.mean()))


def ratio(numerator: float, denominator: float) -> float | None:
    """numerator / denominator, None when the baseline is zero (nothing to compare with)."""
    return None if denominator == 0 else numerator / denominator


class Progress:
    """`[ 12s] engine: ring 1000 transitions (ours)` on stderr; silent when quiet."""

    def __init__(self, quiet: bool = False) -> None:
        self.quiet = quiet
        self.began = time.monotonic()
        self.tty = sys.stderr.isatty()

    def __call__(self, message: str) -> None:
        if self.quiet:
            return
        line = f"[{time.monotonic() - self.began:5.0f}s] {message}"
        if self.tty:
            print("\r\033[K" + line[:150], end="", file=sys.stderr, flush=True)
        else:
            print(line, file=sys.stderr, flush=True)

    def done(self) -> None:
        if self.tty and not self.quiet:
            print(file=sys.stderr, flush=True)
