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

from softplc.core.image import INPUT_AREAS, OUTPUT_AREAS, ProcessImage


def image_digest(image: ProcessImage) -> str:
    """A digest of the output and memory areas. The 32/64-bit areas (issue 30) join it only
    while they hold something, so traces recorded before them replay unchanged."""
    h = hashlib.blake2b(digest_size=8)
    for area in OUTPUT_AREAS:
        values = getattr(image, area)
        if area in _LONG_AREAS and not values.any():
            continue
        h.update(np.ascontiguousarray(values).tobytes())
    return h.hexdigest()


_LONG_AREAS = frozenset({"qd", "md", "ql", "ml"})


def input_changes(now: ProcessImage, before: ProcessImage | None) -> dict[str, dict[str, int]]:
    """Per input area, the locations that changed and their raw bits (JSON integers, exact
    for 64-bit long words too)."""
    out: dict[str, dict[str, int]] = {}
    for area in INPUT_AREAS:
        cur = getattr(now, area)
        if before is not None and cur.tobytes() == getattr(before, area).tobytes():
            continue
        idx = (np.flatnonzero(cur) if before is None
               else np.flatnonzero(cur != getattr(before, area)))
        if len(idx):
            out[area] = {str(i): int(cur[i]) for i in idx.tolist()}
    return out


# One encoder for every record: json.dumps with options builds a new one per call.
_CANONICAL = json.JSONEncoder(sort_keys=True, separators=(",", ":"))


class TraceWriter:
    """Writes one line per scan (when given a path) and keeps the running sha256."""

    def __init__(self, path: str | Path | None = None) -> None:
        self._file: IO[str] | None = open(path, "w", encoding="utf-8") if path else None  # noqa: SIM115
        self._sha = hashlib.sha256()
        self.lines = 0

    @property
    def writes_file(self) -> bool:
        """Whether records go to a file (the readable `extra` part is only written there)."""
        return self._file is not None

    def record(self, record: dict[str, Any], timing: dict[str, int] | None = None,
               extra: dict[str, Any] | None = None) -> None:
        """`timing` and `extra` (output symbols that changed: "q", new diagnostics: "diag")
        go in the file but not in the hash: golden hashes do not move when they are added."""
        self._line(_CANONICAL.encode(record), record, timing, extra)

    def steady(self, k: int, t: int, out: str, state: str) -> None:
        """The record of a scan in which nothing but time passed ({"in": {}, "k", "out",
        "state", "t"}), formatted as the canonical JSON of record() would be, without it:
        most scans are such, and the encoder was the trace's whole cost (issue 15.5).
        `out` and `state` are plain ASCII words (a hex digest, a state name): no escaping."""
        self._line(f'{{"in":{{}},"k":{k},"out":"{out}","state":"{state}","t":{t}}}',
                   None, None, None)

    def _line(self, canonical: str, record: dict[str, Any] | None,
              timing: dict[str, int] | None, extra: dict[str, Any] | None) -> None:
        self._sha.update((canonical + "\n").encode())
        self.lines += 1
        if self._file is not None:
            if timing or extra:
                assert record is not None
                record = {**record, **(extra or {}), **({"timing": timing} if timing else {})}
                canonical = _CANONICAL.encode(record)
            self._file.write(canonical + "\n")

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
