"""The state an engine runs on, shared by its parts.

Owns: the NetState (replaceable from outside: an online change hands over another), the
marking as plain ints sharing its memory, and whether its token counts are still to be
checked against the limits.
Does not know: enabling, selection, firing, outputs.
"""

from __future__ import annotations

from collections.abc import MutableSequence

from softplc.core.net import IntArray, NetState


def counts_view(marking: IntArray) -> MutableSequence[int]:
    """Plain-int element access to the marking, sharing its memory: indexing the numpy array
    costs ~3x more and yields numpy scalars (bench: engine scaling)."""
    try:
        return memoryview(marking)  # type: ignore[arg-type, return-value]
    except TypeError:  # not a buffer (a list given by a caller): use it as it is
        return marking  # type: ignore[return-value]


class Live:
    """The NetState and its plain-int view; `high` says the counts may be past the limits."""

    __slots__ = ("_m", "_marr", "high", "state")

    def __init__(self, state: NetState) -> None:
        self.state = state
        self._marr = state.marking
        self._m = counts_view(self._marr)
        # Total above limits.place_tokens (any round may concentrate it), or not known yet:
        # the first round checks and learns it.
        self.high = True

    def view(self) -> MutableSequence[int]:
        """The marking as plain ints; re-bound when the state or its array was replaced."""
        if self.state.marking is not self._marr:
            self._marr = self.state.marking
            self._m = counts_view(self._marr)
            self.high = True  # another marking: its counts are checked after the next round
        return self._m
