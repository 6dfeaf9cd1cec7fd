"""How much the fuzz tests try, and where they record it.

`SOFTPLC_FUZZ_SCALE` (default 1) multiplies every count: `make test` runs the bounded CI
budget, `make fuzz` a long run. `SOFTPLC_FUZZ_REPORT`, when set, names a file that gets one
JSON line per fuzz test (what it sent, what it found) for RELIABILITY.md.
"""

from __future__ import annotations

import json
import os
import time
from typing import Any

SCALE_ENV = "SOFTPLC_FUZZ_SCALE"
REPORT_ENV = "SOFTPLC_FUZZ_REPORT"
SEED_ENV = "SOFTPLC_FUZZ_SEED"


def scale() -> int:
    try:
        return max(1, int(os.environ.get(SCALE_ENV, "1")))
    except ValueError:
        return 1


def scaled(n: int) -> int:
    """`n` at scale 1; `n * SOFTPLC_FUZZ_SCALE` in a long run."""
    return n * scale()


def seed(default: int) -> int:
    """A fixed seed in CI (reproducible); `SOFTPLC_FUZZ_SEED` explores other streams."""
    value = os.environ.get(SEED_ENV, "")
    return int(value) if value.strip().lstrip("-").isdigit() else default


def record(test: str, **figures: Any) -> None:
    """Append one JSON line {test, scale, seed?, figures...} to $SOFTPLC_FUZZ_REPORT."""
    path = os.environ.get(REPORT_ENV)
    if not path:
        return
    line = {"test": test, "scale": scale(), "at": time.strftime("%Y-%m-%dT%H:%M:%S"),
            **figures}
    with open(path, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(line, sort_keys=True) + "\n")
