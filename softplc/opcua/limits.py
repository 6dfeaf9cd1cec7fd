"""The bounds of the OPC UA server's doors, and reading a request's size before it is decoded.

Owns: the limits (connections, per peer, the unactivated-connection timeout, sessions,
subscriptions, monitored items, operations per request, message and chunk sizes, the
publishing interval) with their defaults (docs/opcua.md, "Limits"), the counts of what the
door refused, and `operations`: how many operations a request asks for, read from the
array length in its encoded body without decoding the array (a Read of 200,000 nodes is
refused for the cost of reading four bytes, not of decoding 200,000 structures).
Does not know: sockets, asyncio, sessions.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, fields
from functools import partial
from typing import Final

from asyncua import ua
from asyncua.common.utils import Buffer, NotEnoughData
from asyncua.ua.ua_binary import extensionobject_from_binary, struct_from_binary

from softplc.opcua.ids import numeric_id


@dataclass(frozen=True, slots=True)
class OpcUaLimits:
    """Every field is a bound; docs/opcua.md has the table with the reasons."""

    max_connections: int = 32
    max_per_peer: int = 16
    # Seconds a connection may stay without an activated session (asyncua: 30).
    activation_timeout_s: float = 5.0
    # A connection is live while its activated session made a request this recently:
    # live connections are never evicted (hmi/admission.py, the same rule as Modbus).
    live_window_s: float = 10.0
    max_sessions: int = 32
    max_session_timeout_s: float = 60.0  # a client asking for an hour gets this
    max_subscriptions: int = 64
    max_subscriptions_per_session: int = 4
    max_monitored_items: int = 2_000  # over all subscriptions of all sessions
    min_publishing_interval_ms: float = 50.0
    max_nodes_per_read: int = 2_000
    max_nodes_per_write: int = 1_000
    max_nodes_per_browse: int = 1_000
    max_methods_per_call: int = 100
    max_monitored_items_per_call: int = 1_000
    max_nodes_per_other: int = 1_000  # TranslateBrowsePaths, RegisterNodes, BrowseNext, ...
    chunk_bytes: int = 65_535  # largest message chunk (the negotiated receive buffer)
    max_message_bytes: int = 1 << 20  # a whole request, all chunks (1 MiB, like the HTTP body)
    max_queued_chunks: int = 32  # per connection, received but not yet processed

    def __post_init__(self) -> None:
        problems = [f"{f.name} must be > 0, got {getattr(self, f.name)}"
                    for f in fields(self) if not getattr(self, f.name) > 0]
        if self.chunk_bytes < 8192:  # Part 6: a receive buffer is at least 8192 bytes
            problems.append(f"chunk_bytes must be >= 8192, got {self.chunk_bytes}")
        if problems:
            raise ValueError("; ".join(problems))

    @property
    def max_chunk_count(self) -> int:
        return -(-self.max_message_bytes // self.chunk_bytes)


@dataclass(frozen=True, slots=True)
class DoorStats:
    """What the door did since start (each a count); a new value at every change."""

    admitted: int = 0
    evicted: int = 0  # closed to make room: never activated, or idle longest
    refused: int = 0  # every slot of the pool was live
    not_activated: int = 0  # closed after activation_timeout_s without a session
    oversized: int = 0  # a chunk or message over its bound: connection closed
    requests_refused: int = 0  # too many operations, sessions, subscriptions or items
    untrusted: int = 0  # a secure channel with a certificate not in the trust list: closed


_I32: Final = struct.Struct("<i")


def _count_at(body: Buffer, skip: int) -> int:
    data = body.copy()
    data.skip(skip)
    count: int = _I32.unpack(data.read(4))[0]
    return max(count, 0)  # -1 is a null array


def _browse_count(body: Buffer) -> int:
    data = body.copy()
    struct_from_binary(ua.ViewDescription, data)
    data.skip(4)  # RequestedMaxReferencesPerNode
    return _count_at(data, 0)


def _history_count(body: Buffer) -> int:
    data = body.copy()
    extensionobject_from_binary(data)  # the details: one structure, not per node
    data.skip(5)  # TimestampsToReturn, ReleaseContinuationPoints
    return _count_at(data, 0)


def _encoding(name: str) -> ua.NodeId:
    return numeric_id(getattr(ua.ObjectIds, f"{name}Request_Encoding_DefaultBinary"))


# Per request type: which limit field applies and the byte offset of the operation array
# after the request header (Part 4's parameter layouts; 12 = MaxAge + TimestampsToReturn).
_FIXED: Final = {
    "Read": ("max_nodes_per_read", 12),
    "Write": ("max_nodes_per_write", 0),
    "Call": ("max_methods_per_call", 0),
    "CreateMonitoredItems": ("max_monitored_items_per_call", 8),
    "ModifyMonitoredItems": ("max_monitored_items_per_call", 8),
    "DeleteMonitoredItems": ("max_monitored_items_per_call", 4),
    "SetMonitoringMode": ("max_monitored_items_per_call", 8),
    "SetTriggering": ("max_monitored_items_per_call", 8),
    "TranslateBrowsePathsToNodeIds": ("max_nodes_per_other", 0),
    "RegisterNodes": ("max_nodes_per_other", 0),
    "UnregisterNodes": ("max_nodes_per_other", 0),
    "BrowseNext": ("max_nodes_per_other", 1),
    "DeleteSubscriptions": ("max_nodes_per_other", 0),
    "SetPublishingMode": ("max_nodes_per_other", 1),
    "Publish": ("max_nodes_per_other", 0),
}
_PARSED: Final[dict[str, tuple[str, Callable[[Buffer], int]]]] = {
    "Browse": ("max_nodes_per_browse", _browse_count),
    "HistoryRead": ("max_nodes_per_other", _history_count),
}
_RULES: Final[dict[ua.NodeId, tuple[str, Callable[[Buffer], int]]]] = {
    **{_encoding(name): (field, partial(_count_at, skip=at))
       for name, (field, at) in _FIXED.items()},
    **{_encoding(name): rule for name, rule in _PARSED.items()},
}


def operations(typeid: ua.NodeId, body: Buffer, limits: OpcUaLimits) -> tuple[int, int] | None:
    """(operations asked for, the limit) of a request whose parameters start at `body`, or
    None for a request type without an operation array. A body too short for its array
    counts as 0: asyncua's own decoding then refuses it."""
    rule = _RULES.get(typeid)
    if rule is None:
        return None
    field, count = rule
    try:
        asked = count(body)
    except (NotEnoughData, struct.error, ua.UaError):
        asked = 0
    return asked, int(getattr(limits, field))
