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
    """HOST:PORT, the host as a socket takes it: an IPv6 address is written in brackets
    ([::1]:8080, RFC 3986) and bound without them."""
    if text in ("off", "none"):
        return None
    host, _, port = text.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not port.isdigit() or "[" in host or "]" in host:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT ([::1]:PORT for IPv6) or off, "
                                         f"got {text!r}")
    return (host or "127.0.0.1", int(port))
