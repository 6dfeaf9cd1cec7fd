"""What one audit append costs, the code of a base revision beside the working tree.

`python -m tests.security.append_figures [--base REV] [--runs N]` extracts `softplc/` of REV
(default HEAD~1) with `git archive`, then in a process per tree and run appends 200 records to
a fresh trail in a directory on this repository's disk (not /tmp: tmpfs has no fsync to pay)
and prints the median and p99 of one append in ms, base and working tree taking turns. Not a
test: tests/security/test_durable_writes.py holds the behaviour (the head written durably).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
APPENDS = 200
_MEASURE = f"""
import json, statistics, sys, tempfile, time
from softplc.security.audit import AuditTrail
with tempfile.TemporaryDirectory(dir={str(ROOT)!r}) as where:
    trail, took = AuditTrail(where), []
    for i in range({APPENDS}):
        start = time.perf_counter()
        trail.append({{"action": "figure", "outcome": "applied", "detail": {{"i": i}}}})
        took.append((time.perf_counter() - start) * 1e3)
took.sort()
print(json.dumps([statistics.median(took), took[int(len(took) * 0.99)]]))
"""


def _tree(rev: str, into: Path) -> Path:
    archive = subprocess.run(["git", "archive", "--format=tar", rev, "softplc"], cwd=ROOT,
                             check=True, capture_output=True).stdout
    tar = into / "softplc.tar"
    tar.write_bytes(archive)
    with tarfile.open(tar) as handle:
        handle.extractall(into, filter="data")
    return into


def _run(path: Path) -> tuple[float, float]:
    env = {**os.environ, "PYTHONPATH": str(path)}
    out = subprocess.run([sys.executable, "-c", _MEASURE], env=env, check=True,
                         capture_output=True, text=True, timeout=300).stdout
    median, p99 = json.loads(out)
    return median, p99


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--base", default="HEAD~1")
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        base = _tree(args.base, Path(scratch))
        for _ in range(args.runs):
            for name, path in ((args.base, base), ("working tree", ROOT)):
                median, p99 = _run(path)
                print(f"{name:>14}: append median {median:.2f} ms, p99 {p99:.2f} ms")


if __name__ == "__main__":
    main()
