"""How one benchmark figure reads in a table cell, in the terminal and in BENCHMARKS.md.

Owns: number formatting (3 significant digits, thousands separators, a dash for nothing),
the verdict words, a value with its unit, picking one statistic out of a figure.
Does not know: the layout of any table.
"""

from __future__ import annotations

from typing import Any


def fmt(value: Any) -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3g}" if abs(value) < 1000 else f"{value:,.0f}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


def verdict(met: bool | None) -> str:
    return {True: "met", False: "MISSED", None: "not measured"}[met]


def with_unit(value: Any, unit: str) -> str:
    if value is None:
        return "—"
    return f"{fmt(value)}x" if unit == "x" else f"{fmt(value)} {unit}"


def stat(figures: Any, key: str) -> Any:
    """One statistic (median, p99, ...) of a figure, None when the figure is missing."""
    return figures.get(key) if isinstance(figures, dict) else None
