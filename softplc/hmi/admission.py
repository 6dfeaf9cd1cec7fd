"""Who gets a Modbus connection slot when the slave is full: admit, evict or refuse.

Owns: the connection limits (total cap, per-peer cap, what "live" means) and the decision
for one new connection, from plain values (peer, times). Pure: times are arguments.
Does not know: sockets, asyncio, pymodbus, Modbus frames.

Rule (docs/modbus.md, "Connections"): a connection is *live* while its last complete request
is younger than `live_window_s`; one that never sent a complete request is never live. A new
connection that fits both caps is admitted. Otherwise the pool is the new peer's own
connections (its per-peer cap is reached) or else every connection (the total cap is
reached), and the pool's non-live connection idle longest is evicted to make room, taken
from the peer holding most slots first, so that a flood from one address evicts its own
connections before a quiet HMI's. Only when every connection of the pool is live is the
new one refused. So idle, half-open or trickling (slowloris) connections never lock a
well-behaved HMI out, and a client polling once a minute keeps its slot only while nobody
else needs it.
"""

from __future__ import annotations

import enum
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

DEFAULT_MAX_CONNECTIONS = 16
DEFAULT_MAX_PER_PEER = 8
DEFAULT_IDLE_TIMEOUT_S = 60.0
# Real HMIs poll every 0.1-2 s; 10 s leaves room for a slow SCADA poll and a retry.
DEFAULT_LIVE_WINDOW_S = 10.0


class Verdict(enum.Enum):
    ADMIT = "admit"
    EVICT = "evict"  # admit, after closing `victim`
    REFUSE = "refuse"


@dataclass(frozen=True, slots=True)
class Limits:
    max_connections: int = DEFAULT_MAX_CONNECTIONS
    max_per_peer: int = DEFAULT_MAX_PER_PEER
    idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S
    live_window_s: float = DEFAULT_LIVE_WINDOW_S

    def __post_init__(self) -> None:
        problems = []
        if self.max_connections < 1:
            problems.append(f"max_connections must be >= 1, got {self.max_connections}")
        if self.max_per_peer < 1:  # above max_connections it never binds: allowed
            problems.append(f"max_per_peer must be >= 1, got {self.max_per_peer}")
        if not self.idle_timeout_s > 0:
            problems.append(f"idle_timeout_s must be > 0, got {self.idle_timeout_s}")
        if not self.live_window_s > 0:
            problems.append(f"live_window_s must be > 0, got {self.live_window_s}")
        if problems:
            raise ValueError("; ".join(problems))


@dataclass(frozen=True, slots=True)
class Slot:
    """An admitted connection as the rule sees it."""

    key: str
    peer: str  # IP address, without the port
    connected_s: float
    last_request_s: float | None = None  # last complete request; None before the first

    @property
    def last_active_s(self) -> float:
        return self.connected_s if self.last_request_s is None else self.last_request_s

    def is_live(self, now_s: float, live_window_s: float) -> bool:
        return self.last_request_s is not None and now_s - self.last_request_s < live_window_s


@dataclass(frozen=True, slots=True)
class ConnectionStats:
    """Connection counts since start: what the admission rule and the idle timeout did."""

    admitted: int = 0
    evicted: int = 0  # closed to make room for a new connection
    refused: int = 0  # every slot of the pool was live
    idle_closed: int = 0  # no complete request within the idle timeout


@dataclass(frozen=True, slots=True)
class Decision:
    verdict: Verdict
    reason: str
    victim: str | None = None  # the Slot.key to close when verdict is EVICT


def decide(peer: str, slots: Sequence[Slot], now_s: float, limits: Limits) -> Decision:
    """What to do with a new connection from `peer`, given the admitted `slots`."""
    own = [slot for slot in slots if slot.peer == peer]
    if len(own) >= limits.max_per_peer:
        pool, reason = own, f"per-peer limit ({limits.max_per_peer}) of {peer}"
    elif len(slots) >= limits.max_connections:
        pool, reason = list(slots), f"connection limit ({limits.max_connections})"
    else:
        return Decision(Verdict.ADMIT, "a slot is free")
    victim = _victim(pool, Counter(slot.peer for slot in slots), now_s, limits.live_window_s)
    if victim is None:
        return Decision(Verdict.REFUSE, f"{reason}: every connection is live")
    return Decision(Verdict.EVICT, f"{reason}: evicting the connection idle longest", victim.key)


def _victim(
    pool: Iterable[Slot], per_peer: Counter[str], now_s: float, live_window_s: float
) -> Slot | None:
    idle = [slot for slot in pool if not slot.is_live(now_s, live_window_s)]
    if not idle:
        return None
    return min(idle, key=lambda slot: (-per_peer[slot.peer], slot.last_active_s, slot.key))
