"""What one firing round returns.

Owns: Step, the value of one round, and IDLE, the round that did nothing.
Does not know: how a round is run (engine.py).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Step:
    """What one round did. `fired` is in step order; `completed` lists three-phase ends."""

    fired: tuple[int, ...]
    completed: tuple[int, ...]
    writes: tuple[tuple[str, int | float], ...]  # (symbol, value) in order: last writer wins
    emitted: tuple[str, ...]
    changed_places: frozenset[int]


IDLE = Step((), (), (), (), frozenset())  # a round that fired, completed and wrote nothing
