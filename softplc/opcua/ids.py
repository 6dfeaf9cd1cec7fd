"""Typed constructors of asyncua's NodeId and StatusCode.

Owns: nothing but the conversions; asyncua types those fields with its own int/str
subclasses (ua.Int32, ua.Int16, ua.String, ua.UInt32), which a plain int or str does not
satisfy under mypy --strict.
Does not know: the address space, the server, the driver.
"""

from __future__ import annotations

from asyncua import ua


def numeric_id(identifier: int, ns: int = 0) -> ua.NodeId:
    """A numeric node id (namespace 0 by default: the standard's ids)."""
    return ua.NodeId(ua.Int32(identifier), ua.Int16(ns))


def string_id(text: str, ns: int) -> ua.NodeId:
    """A string node id in namespace `ns`."""
    return ua.NodeId(ua.String(text), ua.Int16(ns))


def status_code(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))
