"""What the scan thread did between scans for the downloads (runtime/download.py), per stage: how
many steps, how long in all and at most, and how many ended past their limit (a step that may
have cost the next scan its slot). Read in status (`download_steps`) and by the online-change
bench (issue 40 item 8: find where the scan loses slots before changing anything).

Owns: StepLog. Does not know: what a step does.
"""

from __future__ import annotations

from typing import Any


class StepLog:
    """Per stage: [steps, total ns, longest ns, steps that ended past the limit]."""

    __slots__ = ("stages",)

    def __init__(self) -> None:
        self.stages: dict[str, list[int]] = {}

    def note(self, stage: str, began_ns: int, ended_ns: int, limit_ns: int | None) -> None:
        took = ended_ns - began_ns
        row = self.stages.get(stage)
        if row is None:
            row = self.stages[stage] = [0, 0, 0, 0]
        row[0] += 1
        row[1] += took
        if took > row[2]:
            row[2] = took
        if limit_ns is not None and ended_ns > limit_ns:
            row[3] += 1

    def as_dict(self) -> dict[str, Any]:
        return {stage: {"steps": n, "total_ms": round(total / 1e6, 2),
                        "longest_us": round(longest / 1e3), "past_limit": late}
                for stage, (n, total, longest, late) in self.stages.items()}
