"""Resource limits of a running program: no net can exhaust the machine.

Owns: the limits (arc weight, tokens per place and in total, coloured tokens per place and in
total, binding tries per scan), their defaults, the hard maxima a program's `limits:` section
may not exceed, and the names of the keys of that section.
Does not know: YAML (program/spec.py parses the section), the engine (core/engine/counts.py checks
the run-time limits and raises PlcFault(FaultCode.LIMIT, ...)).

Why these numbers (docs/programs.md, "Limits"):
- weight 1,000,000: one firing moves at most a million plain tokens; a coloured output arc
  additionally may not exceed coloured_place (each unit of its weight is a record in memory).
- place_tokens 1,000,000,000 and total_tokens 10,000,000,000: a plain marking is an int64
  count, cheap in memory; the limit catches a runaway generator long before an int64 could
  wrap (2**63 ~ 9.2e18) and still counts a part a second for 30 years.
- coloured_place 10,000 and coloured_total 100,000: a record costs about 300-400 bytes in
  Python and about 30-60 bytes in each retain snapshot; 100,000 records are ~40 MB and a
  few-MB snapshot. A coloured arc of weight 2000 that grows every scan faults at the fifth
  scan, not after 690 MB.
- bindings_per_scan 50,000: a binding try evaluates a guard (~1-3 us), so one scan's binding
  search stays within ~0.1 s, and the transition that searched is named.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace


@dataclass(frozen=True, slots=True)
class Limits:
    weight: int = 1_000_000  # any arc, checked at compile time
    place_tokens: int = 1_000_000_000  # tokens (count) in one place
    total_tokens: int = 10_000_000_000  # tokens (count) in the whole net
    coloured_place: int = 10_000  # records in one coloured place
    coloured_total: int = 100_000  # records in the whole net
    bindings_per_scan: int = 50_000  # binding combinations tried in one round

    def with_overrides(self, overrides: dict[str, int]) -> Limits:
        return replace(self, **overrides)


DEFAULT = Limits()
# A program's `limits:` may lower any limit, or raise it up to these.
HARD = Limits(weight=1_000_000, place_tokens=1_000_000_000_000,
              total_tokens=1_000_000_000_000_000, coloured_place=1_000_000,
              coloured_total=1_000_000, bindings_per_scan=1_000_000)
KEYS: tuple[str, ...] = tuple(f.name for f in fields(Limits))


def override_problem(key: object, value: object) -> str | None:
    """None if `key: value` is a valid line of a program's `limits:`, else what is wrong."""
    if key not in KEYS:
        return f"unknown limit {key!r}; expected one of {', '.join(KEYS)}"
    top = getattr(HARD, str(key))
    if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= top:
        default = getattr(DEFAULT, str(key))
        return f"limit {key} must be a whole number from 1 to {top:,} (default {default:,})"
    return None
