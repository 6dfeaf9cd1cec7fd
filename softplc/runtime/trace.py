"""Scan traces as JSON Lines: record every scan, read them back for replay.

Owns: the trace record format (inputs that changed, commands, HMI writes, fired transitions,
marking changes, output changes, a digest of the whole output image, timing) and the trace's
sha256 (over everything but wall-clock timing, so identical runs hash identically).
Does not know: how scans run.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from softplc.core.image import OUTPUT_AREAS, ProcessImage


def image_digest(image: ProcessImage) -> str:
    h = hashlib.blake2b(digest_size=8)
    for area in OUTPUT_AREAS:
        h.update(np.ascontiguousarray(getattr(image, area)).tobytes())
    return h.hexdigest()


def input_changes(now: ProcessImage, before: ProcessImage | None) -> dict[str, dict[str, int]]:
    out: dict[str, dict[str, int]] = {}
    for area in ("ix", "iw"):
        cur = getattr(now, area)
        if before is not None and cur.tobytes() == getattr(before, area).tobytes():
            continue
        idx = (np.flatnonzero(cur) if before is None
               else np.flatnonzero(cur != getattr(before, area)))
        if len(idx):
            out[area] = {str(i): int(cur[i]) for i in idx.tolist()}
    return out


class TraceWriter:
    """Writes one line per scan (when given a path) and keeps the running sha256."""

    def __init__(self, path: str | Path | None = None) -> None:
        self._file: IO[str] | None = open(path, "w", encoding="utf-8") if path else None  # noqa: SIM115
        self._sha = hashlib.sha256()
        self.lines = 0

    def record(self, record: dict[str, Any], timing: dict[str, int] | None = None,
               extra: dict[str, Any] | None = None) -> None:
        """`timing` and `extra` (output symbols that changed: "q", new diagnostics: "diag")
        go in the file but not in the hash: golden hashes do not move when they are added."""
        canonical = json.dumps(record, sort_keys=True, separators=(",", ":"))
        self._sha.update(canonical.encode() + b"\n")
        self.lines += 1
        if self._file is not None:
            if timing or extra:
                record = {**record, **(extra or {}), **({"timing": timing} if timing else {})}
            self._file.write(json.dumps(record, sort_keys=True, separators=(",", ":")) + "\n")

    @property
    def sha256(self) -> str:
        return self._sha.hexdigest()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def read_trace(path: str | Path) -> Iterator[dict[str, Any]]:
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, 1):
            try:
                yield json.loads(line)
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}:{number}: not a trace record ({exc.msg})") from None
