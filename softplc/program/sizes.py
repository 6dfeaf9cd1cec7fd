"""Bounds on a program's size once its subnets are expanded: a download costs little past them.

Owns: the size limits (places, transitions, arcs, subnet instances, expression characters,
characters of text read), their defaults, and `Sizes`, the count the parser (spec.py) steps
as it expands, which stops the expansion at the first item over a limit with that item's
location. Does not know: YAML, what a place or a guard means.

Why these numbers (docs/programs.md, "Size limits"): the shipped programs have tens of
places; the online-change bench downloads a ring of 10,000 transitions and 10,001 places,
which must pass. A 2.2 KB bundle of 10 x 10 x 10 subnet instances of a 100-transition leaf
expanded to 100,000 transitions (scan process 41 -> 350 MiB); a 900 KB program of 70,000
places took the compile process to 6,990 MiB. Twice the bench's ring is still a compile of
about two seconds and a net the scan runs.
They are the runtime's, not the program's: a program's `limits:` cannot raise them.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from softplc.core.errors import SoftplcError
from softplc.core.problems import Problem


@dataclass(frozen=True, slots=True)
class SizeLimits:
    places: int = 16_000
    transitions: int = 16_000
    arcs: int = 64_000  # input, output, read and inhibitor arcs together
    subnets: int = 1_000  # subnet instances, nested ones included
    expression_chars: int = 2_000_000  # guards, actions and token fields, summed
    text_chars: int = 4_000_000  # the program and each subnet instance's file, as read


DEFAULT_SIZES = SizeLimits()
WHAT = {"places": "places", "transitions": "transitions", "arcs": "arcs",
        "subnets": "subnet instances", "expression_chars": "characters of expressions",
        "text_chars": "characters of program text read (each subnet instance's file again)"}
assert set(WHAT) == {f.name for f in fields(SizeLimits)}


class SizeExceeded(SoftplcError):
    """The expansion stopped: `problem` is located at the item that went over."""

    def __init__(self, problem: Problem) -> None:
        super().__init__(str(problem))
        self.problem = problem


class Sizes:
    """What the expansion has produced so far, against `limits`."""

    def __init__(self, limits: SizeLimits = DEFAULT_SIZES) -> None:
        self.limits = limits
        self.counts = dict.fromkeys(WHAT, 0)

    def add(self, key: str, n: int, file: str, line: int, path: str) -> None:
        """Count `n` more of `key`; past the limit, raise SizeExceeded located here."""
        total = self.counts[key] + n
        self.counts[key] = total
        limit = getattr(self.limits, key)
        if total > limit:
            raise SizeExceeded(Problem(file, line, path, over(key, total, limit)))


def over(key: str, total: int, limit: int) -> str:
    """The wording of a size refusal: what, the limit's name and its value."""
    return (f"the program is too large: {total:,} {WHAT[key]} once subnets are expanded, "
            f"over the size limit {key} = {limit:,} (docs/programs.md, size limits)")


def count_problem(file: str, line: int, counts: dict[str, int],
                  limits: SizeLimits = DEFAULT_SIZES) -> Problem | None:
    """For a net whose counts are known before it is built (a PNML import): the first count
    over its limit, located at `line`."""
    for key, n in counts.items():
        if n > getattr(limits, key):
            return Problem(file, line, "", over(key, n, getattr(limits, key)))
    return None
