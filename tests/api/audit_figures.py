"""Figures of the HTTP audit trail's costs, the code of a base revision beside the working tree.

`python -m tests.api.audit_figures [--base REV]` extracts `softplc/` of REV (default HEAD)
with `git archive`, then measures each tree in its own process against a real ApiServer on
127.0.0.1 port 0 and prints one table:
- GET /api/v1/status with a full trail (8 files of 1 MiB and a newest one half full,
  ~24,000 records): 50 requests, each after one record appended (a check due each time: the
  5 s interval set to 0), median and p99 in ms; the full verifications and lines parsed;
- 1,000 refused requests (wrong bearer keys; POSTs without credentials): the records and
  fsyncs they cost, counted until the server has stopped (the summaries written at stop).
Also the best of 3 full verifications of that trail, and of 3 checks of one record appended
(where the tree can go on from a verification's end). Not a test: test_audit_refusals.py and
test_audit_chain.py hold the behaviour.
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import http.client
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
ENTRY: dict[str, Any] = {"user": "op", "role": "operator", "via": "key", "peer": "127.0.0.1",
                         "iface": "http", "action": "PUT symbols/hold", "outcome": "applied",
                         "status": 200, "detail": {"value": 1, "message": "written"}}


def fill(state: Path, files: int, max_bytes: int) -> int:
    """A trail of `files` full files in the trail's own format (written at once, no fsync)."""
    from softplc.security.audit import GENESIS, canonical, utc_now

    state.mkdir(parents=True, exist_ok=True)
    seq, prev = 0, GENESIS
    for n in range(files - 1, -1, -1):
        lines, size = [], 0
        while size < (max_bytes if n else max_bytes // 2):  # the newest: room to grow
            seq += 1
            record = {**ENTRY, "seq": seq, "time": utc_now(), "prev": prev}
            record["hash"] = prev = hashlib.sha256(canonical(record).encode()).hexdigest()
            lines.append(canonical(record) + "\n")
            size += len(lines[-1])
        (state / ("audit.jsonl" if n == 0 else f"audit.{n}.jsonl")).write_text("".join(lines))
    return seq


class Served:
    """An ApiServer in front of a board with one document, on a loop in a thread."""

    def __init__(self, state: Path) -> None:
        from softplc.api.server import ApiServer
        from softplc.core.image import ImageSizes
        from softplc.runtime.shared.board import StatusBoard
        from softplc.runtime.shared.channel import Channel
        from softplc.runtime.shared.shm import SnapshotReader, SnapshotWriter

        self.channel = Channel()
        self.writer = SnapshotWriter.create(ImageSizes())
        self.board = StatusBoard.create(f"softplc-fig-{uuid.uuid4().hex[:12]}")
        self.board.publish({"state": "STOPPED", "scan_count": 0})
        self.reader = SnapshotReader.attach(self.writer.name, self.writer.sizes)
        self.server = ApiServer(self.channel, self.reader, self.board, port=0, state_dir=state)
        self.loop = asyncio.new_event_loop()
        threading.Thread(target=self.loop.run_forever, daemon=True).start()
        self.call(self.server.start())
        self.port = self.server.bound_port

    def call(self, coro: Any) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(60)

    def stop(self) -> None:
        self.call(self.server.stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.channel.close()
        self.reader.close()
        self.writer.close()
        self.writer.unlink()
        self.board.close()


def status_ms(served: Served, trail: Any, requests: int) -> list[float]:
    conn = http.client.HTTPConnection("127.0.0.1", served.port, timeout=60)
    times = []
    for n in range(requests + 1):
        trail.append({**ENTRY, "detail": {"value": n}})
        t0 = time.perf_counter()
        conn.request("GET", "/api/v1/status")
        answer = conn.getresponse()
        body = json.loads(answer.read())
        assert answer.status == 200 and "audit" in body, body
        if n:
            times.append((time.perf_counter() - t0) * 1e3)
            continue
        while body["audit"]["ok"] is None:  # the first check, started by the first request
            time.sleep(0.05)
            conn.request("GET", "/api/v1/status")
            body = json.loads(conn.getresponse().read())
    conn.close()
    return times


def verify_ms(trail: Any) -> tuple[float, float | str]:
    """The best of 3 full verifications, and of 3 checks of one appended record from the
    last one's end (where the tree can)."""
    fulls, tails = [], []
    for _ in range(3):
        t0 = time.perf_counter()
        verdict = trail.verify()
        fulls.append((time.perf_counter() - t0) * 1e3)
        resume = getattr(verdict, "resume", None)
        if resume is not None:
            trail.append(ENTRY)
            t0 = time.perf_counter()
            assert trail.verify_tail(resume).parsed == 1
            tails.append((time.perf_counter() - t0) * 1e3)
    return min(fulls), min(tails) if tails else "-"


def flood(port: int, requests: int) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    for n in range(requests):
        if n % 2:
            conn.request("POST", "/api/v1/stop")  # without credentials: 401, denied
        else:
            conn.request("GET", "/api/v1/status", headers={"Authorization": "Bearer nobody.x"})
        answer = conn.getresponse()
        answer.read()
        assert answer.status == 401, answer.status
    conn.close()


def measure(requests: int, refused: int) -> dict[str, Any]:
    """In the tree on sys.path: the figures of this process's softplc."""
    import softplc.api.access as access
    import softplc.security.audit as audit

    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state"
        records = fill(state, audit.KEEP + 1, audit.MAX_BYTES)
        full_ms, tail_ms = verify_ms(audit.AuditTrail(state))
        vars(access)["CHAIN_CHECK_S"] = 0.0  # the base revision's check interval
        served = Served(state)
        watch = getattr(served.server.gate, "watch", None)
        if watch is not None:
            watch.interval_s = 0.0
        trail = served.server.gate.audit
        times = status_ms(served, trail, requests)
        full_checks = getattr(watch, "full_checks", "-")
        parsed = getattr(watch, "parsed", "-")
        served.stop()
    fsyncs = [0]
    real_fsync = os.fsync

    def counted(fd: int) -> None:
        fsyncs[0] += 1
        real_fsync(fd)

    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp) / "state"
        served = Served(state)
        before = len(audit.AuditTrail(state).records())
        audit.os.fsync = counted  # type: ignore[attr-defined]
        t0 = time.perf_counter()
        flood(served.port, refused)
        flood_s = time.perf_counter() - t0
        during = len(audit.AuditTrail(state).records()) - before
        served.stop()
        audit.os.fsync = real_fsync  # type: ignore[attr-defined]
        after = len(audit.AuditTrail(state).records()) - before
        ok = audit.AuditTrail(state).verify().ok
    times.sort()
    return {"trail": records, "full_verify_ms": full_ms, "tail_verify_ms": tail_ms,
            "median_ms": statistics.median(times),
            "p99_ms": times[min(len(times) - 1, round(0.99 * len(times)))],
            "max_ms": times[-1], "full_checks": full_checks, "lines_parsed": parsed,
            "refused": refused, "records_during": during,
            "records_after_stop": after, "fsyncs": fsyncs[0], "flood_s": flood_s,
            "chain_ok": ok}


def run_tree(tree: Path, requests: int, refused: int) -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": f"{tree}{os.pathsep}{ROOT}"}
    done = subprocess.run([sys.executable, "-m", "tests.api.audit_figures", "--measure",
                           str(requests), str(refused)], env=env, cwd=tempfile.gettempdir(),
                          capture_output=True, text=True, timeout=600)
    if done.returncode:
        raise SystemExit(f"{tree}: {done.stderr[-3000:]}")
    figures: dict[str, Any] = json.loads(done.stdout.splitlines()[-1])
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--base", default="HEAD", help="the revision to compare with")
    parser.add_argument("--requests", type=int, default=50)
    parser.add_argument("--refused", type=int, default=1000)
    parser.add_argument("--measure", nargs=2, type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        import softplc

        print(json.dumps({**measure(*args.measure), "softplc": softplc.__file__}))
        return
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "archive", args.base, "softplc"], cwd=ROOT,
                                 capture_output=True, check=True).stdout
        with tarfile.open(fileobj=__import__("io").BytesIO(archive)) as tar:
            tar.extractall(tmp, filter="data")
        rows = {args.base: run_tree(Path(tmp), args.requests, args.refused),
                "working tree": run_tree(ROOT, args.requests, args.refused)}
    keys = ["trail", "full_verify_ms", "tail_verify_ms", "median_ms", "p99_ms", "max_ms",
            "full_checks", "lines_parsed", "refused", "records_during", "records_after_stop",
            "fsyncs", "flood_s", "chain_ok"]
    print(f"{'':20}" + "".join(f"{k:>20}" for k in rows))
    for key in keys:
        cells = [v[key] for v in rows.values()]
        print(f"{key:20}" + "".join(f"{c:>20.1f}" if isinstance(c, float) else f"{c!s:>20}"
                                    for c in cells))


if __name__ == "__main__":
    main()
