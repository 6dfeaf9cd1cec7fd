"""Argument types of the CLI's own commands: durations, counts, HOST:PORT endpoints.

Owns: turning an option's text into a value or an argparse error naming what was expected.
Does not know: which command uses them.
"""

from __future__ import annotations

import argparse

from softplc.core.units import parse_duration_ns


def duration(text: str) -> int:
    try:
        return parse_duration_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def timeout(text: str) -> int:
    if (ns := duration(text)) <= 0:
        raise argparse.ArgumentTypeError(f"expected a duration above 0, got {text!r}")
    return ns


def count(text: str) -> int:
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return int(text)


def endpoint(text: str) -> tuple[str, int] | None:
    if text in ("off", "none"):
        return None
    host, _, port = text.rpartition(":")
    if not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT or off, got {text!r}")
    return (host or "127.0.0.1", int(port))
