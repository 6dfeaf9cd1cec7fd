"""Benchmark section `online_change`: time from an online-change download (HTTP API POST, as
`softplc download --online` sends it) to the first scan of the new net, and the scans missed
meanwhile, for a 10-transition and a 10,000-transition net, PLC running at 1 ms.

Owns: the generated ring nets (one program name, so every download is an online change of
the running program with its marking carried over by place name) and the section's keys.
Does not know: how the scan process compiles or swaps nets (runtime/loop.py, core/scan.py).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable
from typing import Any

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.bench.live import ROOT, LiveRuntime, ScanRecord, run_floor
from softplc.bench.measure import Progress, figures
from softplc.core import online
from softplc.core.engine import Engine
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.net import NetState
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.scan import scan
from softplc.core.snapshot import CommandRequest
from softplc.program.compiler import compile_text
from softplc.runtime.realtime import Realtime, keep_off_scan_cpu, recommended

PROGRAM = "online_bench"
FILE_NAME = "online_bench.yaml"  # resolved under the runtime's programs/ directory
_SETUP_IDS = iter(range(1_000_000, 2_000_000))  # far from the API's ids (1, 2, ...)
FLOOR_S = 5.0  # the empty loop's run, at least
BIG_SETTLE_S = 4.0  # before a net over 1,000 transitions: its change takes up to ~3 s


def ring_program(transitions: int, variant: int) -> str:
    """A ring of `transitions` unguarded transitions and places p0.., one token in p0.
    Variants differ by an unconnected place, so each download is a real change; the places
    of a smaller ring are a prefix of a larger one, so any change carries the token over."""
    lines = [f"program: {PROGRAM}", "io_image: ../io_images/transport.yaml", "places:",
             "  p0: {tokens: 1}"]
    lines += [f"  p{i}: {{}}" for i in range(1, transitions)]
    if variant:
        lines.append(f"  spare{variant}: {{}}")
    lines.append("transitions:")
    lines += [f"  t{i}: {{from: [p{i}], to: [p{(i + 1) % transitions}]}}"
              for i in range(transitions)]
    return "\n".join(lines) + "\n"


def _command(runtime: LiveRuntime, command: Command, text: str | None = None) -> None:
    """Set-up commands go through the channel with a long timeout: a big net compiles for
    longer than the API waits, and set-up is not what is measured."""
    reply = runtime.channel.send_command(
        CommandRequest(next(_SETUP_IDS), command, program_text=text, program_path=FILE_NAME),
        timeout_s=600)
    if not reply.ok:
        raise RuntimeError(f"{command.value} refused: {reply.message}")


def _download_online(runtime: LiveRuntime, api: ApiClient, text: str,
                     timeout_s: float, settle_s: float) -> dict[str, Any]:
    status = runtime.status()
    before, steps_before = status.get("program_hash"), status.get("download_steps") or {}
    quiet_since = time.monotonic_ns() - int(settle_s * 1e9)
    t_request = time.monotonic_ns()
    try:
        outcome = api.download_text(text, online=True, name=FILE_NAME)["message"]
    except (ApiError, ApiUnreachable) as exc:
        outcome = f"error: {exc}"
    t_reply = time.monotonic_ns()
    deadline = time.monotonic() + timeout_s
    # The swap shows on the status board even when the API gave up waiting (503).
    while (status := runtime.status()).get("program_hash") == before:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the online change did not happen within {timeout_s} s")
        time.sleep(0.02)
    return {"t_request_ns": t_request, "t_reply_ns": t_reply, "api": str(outcome),
            "quiet_since_ns": quiet_since,
            "steps": _steps_of(steps_before, status.get("download_steps") or {}),
            "reply": (status.get("compile_process") or {}).get("last_reply")}


def _steps_of(before: dict[str, Any], after: dict[str, Any]) -> dict[str, Any]:
    """This download's steps between scans, per stage (runtime/steplog.py: counts since the
    scan process started; the longest is over its whole life)."""
    out = {}
    for stage, now in after.items():
        was = before.get(stage, {})
        out[stage] = {"steps": now["steps"] - was.get("steps", 0),
                      "total_ms": round(now["total_ms"] - was.get("total_ms", 0), 2),
                      "longest_us": now["longest_us"],
                      "past_limit": now["past_limit"] - was.get("past_limit", 0)}
    return out


def _evaluate(request: dict[str, Any], record: ScanRecord, period_ns: int) -> dict[str, Any]:
    change = next(c for c in record.changes if c["done_ns"] > request["t_request_ns"])
    i = min(change["index"], record.at_ns.size - 1)  # beyond the capacity: the last kept
    t0 = request["t_request_ns"]
    span = (record.at_ns >= t0) & (record.at_ns <= record.at_ns[i])
    # The machine's own noise, side by side: the slots missed in a window as long, just
    # before the request, while nothing was being downloaded (None when that window reaches
    # back into the previous change).
    length = int(record.at_ns[i]) - t0
    quiet_from = request["quiet_since_ns"]
    before = (record.at_ns >= t0 - length) & (record.at_ns < t0)
    return {
        "request_to_first_scan_ms": (change["done_ns"] - t0) / 1e6,
        "request_to_reply_ms": (request["t_reply_ns"] - t0) / 1e6,
        # Every slot skipped from the request to the first scan of the new net (noise of a
        # shared machine included), and those the swap scan itself skipped (the compile).
        "missed_scans": int(record.missed[span].sum()),
        "swap_scan_missed": int(record.missed[i]),
        "missed_scans_before": int(record.missed[before].sum())
        if t0 - length >= quiet_from else None,
        "swap_scan_exec_ms": int(record.exec_ns[i]) / 1e6,  # compile + swap + first scan
        "transitions": change["transitions"], "api": request["api"],
        "steps": request["steps"], "compile_reply": request["reply"],
        "late_slots": _late_slots(record, span, period_ns),
    }


def _late_slots(record: ScanRecord, span: Any, period_ns: int) -> list[dict[str, float]]:
    """The scans of the change's window that missed slots or started over half a period
    late, with their lateness and execution time, in ms from the window's start."""
    at, late, ex, missed = (record.at_ns[span], record.late_ns[span], record.exec_ns[span],
                            record.missed[span])
    if not at.size:
        return []
    return [{"at_ms": round((int(at[k]) - int(at[0])) / 1e6, 1),
             "late_ms": round(int(late[k]) / 1e6, 2), "exec_ms": round(int(ex[k]) / 1e6, 2),
             "missed": int(missed[k])}
            for k in range(at.size) if missed[k] or late[k] > period_ns // 2][:40]


def split_cost_ms(old_transitions: int, new_transitions: int) -> dict[str, float]:
    """Where an online change's time goes, measured in this process: compiling the new net
    (text to CompiledNet, in the compile process) and the swap scan alone (what
    the scan does with the compiled net, its engine tables and carry plan prebuilt)."""
    filename = str(ROOT / "programs" / FILE_NAME)
    old = compile_text(ring_program(old_transitions, 0), filename, ROOT)
    began = time.perf_counter_ns()
    new = compile_text(ring_program(new_transitions, 1), filename, ROOT)
    compiled = time.perf_counter_ns()
    plc = Plc.empty(ProcessImage(old.io.sizes))
    inputs = ProcessImage(old.io.sizes)
    scan(plc, inputs, 0, [ProgramCommand(Command.DOWNLOAD, old), ProgramCommand(Command.START)])
    # As runtime/loop.py hands it over: the engine's tables and the carry plan built first.
    engine, carry_plan = Engine(new, NetState.initial(new)), online.plan(old, new)
    engine.prime()
    swap_began = time.perf_counter_ns()
    scan(plc, inputs, 1_000_000, [ProgramCommand(Command.DOWNLOAD, new, online=True,
                                                 engine=engine, plan=carry_plan)])
    swapped = time.perf_counter_ns()
    if plc.net is not new:
        raise RuntimeError("the online change was refused")
    return {"compile_ms": (compiled - began) / 1e6,
            "swap_and_scan_ms": (swapped - swap_began) / 1e6}


def _drive(runtime: LiveRuntime, sizes: tuple[int, ...], counts: dict[int, int],
           settle_s: float, timeout_s: float,
           progress: Progress) -> list[tuple[int, int, dict[str, Any]]]:
    """The smallest net running, then the online changes: (from size, to size, timings)."""
    _command(runtime, Command.DOWNLOAD, ring_program(min(sizes), 0))
    _command(runtime, Command.START)
    runtime.wait_for_state("RUNNING")
    api = ApiClient(runtime.api_url, timeout_s=timeout_s)
    requests = []
    variant, running = 0, min(sizes)
    for n in sizes:
        for k in range(counts[n]):
            variant = 1 - variant
            progress(f"online_change: download online, {n} transitions ({k + 1}/{counts[n]})")
            # Long enough before a big net for a baseline window as long as its change.
            settle = settle_s if n <= 1000 else max(settle_s, BIG_SETTLE_S)
            time.sleep(settle)
            requests.append((running, n, _download_online(
                runtime, api, ring_program(n, variant), timeout_s, settle)))
            running = n
    time.sleep(settle_s)
    return requests


def _by_size(changes: list[dict[str, Any]], sizes: tuple[int, ...], split_limit: int,
             progress: Progress) -> dict[str, Any]:
    by_size: dict[str, Any] = {}
    for n in sizes:
        mine = [c for c in changes if c["size"] == n]
        latency = figures([c["request_to_first_scan_ms"] for c in mine])
        by_size[str(n)] = {"changes": len(mine), "request_to_first_scan_ms": {
            "median": latency.median, "max": latency.max},
            "missed_scans": max(c["missed_scans"] for c in mine),
            "missed_scans_before": _worst(c["missed_scans_before"] for c in mine)}
        if n <= split_limit:
            progress(f"online_change: compile vs swap cost in-process, {n} transitions")
            by_size[str(n)]["split"] = split_cost_ms(min(sizes), n)
    return by_size


def _session(busy_wait: bool, sizes: tuple[int, ...], counts: dict[int, int], period_ns: int,
             settle_s: float, timeout_s: float, split_limit: int,
             progress: Progress) -> dict[str, Any]:
    """The runtime started, the online changes, the empty loop waiting as the scan did."""
    wait = "busy" if busy_wait else "sleeping"
    # Busy: the scan on a CPU of its own, the rest of the runtime and this driver on the
    # others, as docs/realtime.md recommends on a virtual machine (unpinned, a process the
    # kernel puts on the spinning scan's CPU takes it for a whole tick, 4 ms, now and then).
    # Sleeping: `softplc run`'s defaults.
    realtime = Realtime(busy_wait=True, cpu=recommended().cpu) if busy_wait else Realtime()
    runtime = LiveRuntime(program=None, start=False, plant=None, period_ns=period_ns,
                          modbus=False, capacity_s=300 + 30 * sum(counts.values()),
                          realtime=realtime, keeps_state=True)  # as `softplc run`: boot, retain
    mine = os.sched_getaffinity(0)
    try:
        progress(f"online_change: starting the runtime (scan waiting {wait})")
        runtime.start()
        keep_off_scan_cpu(os.getpid(), realtime)
        requests = _drive(runtime, sizes, counts, settle_s, timeout_s, progress)
        record = runtime.stop()
    finally:
        runtime.stop()
        os.sched_setaffinity(0, mine)
    assert record is not None
    changes = [{"size": n, "from_transitions": old, **_evaluate(r, record, period_ns)}
               for old, n, r in requests]
    by_size = _by_size(changes, sizes, split_limit, progress)
    # The machine's noise once more, side by side: the empty loop on the same clock, waiting
    # the same way, no PLC at all, for as long as the slowest change took (at least FLOOR_S).
    longest_s = max(c["request_to_first_scan_ms"] for c in changes) / 1e3
    floor_s = max(FLOOR_S, min(longest_s * 4, 30.0))
    progress(f"online_change: the empty loop for {floor_s:.0f} s, waiting {wait} (the floor)")
    floor = run_floor(period_ns, floor_s, realtime)
    floor_missed = int(floor.missed.sum())
    return {"wait": wait, "scan_cpu": realtime.cpu,
            "floor": {"seconds": floor_s, "missed": floor_missed,
                      "missed_per_s": floor_missed / floor_s},
            "changes": changes, "by_size": by_size,
            "missed_scans": max(v["missed_scans"] for v in by_size.values()),
            "missed_scans_before": _worst(v["missed_scans_before"] for v in by_size.values())}


def run(quick: bool, progress: Progress, *, sizes: tuple[int, ...] = (10, 10_000),
        repeats: dict[int, int] | None = None, period_ms: int = 1,
        settle_s: float = 0.3, timeout_s: float = 600.0,
        split_up_to: int | None = None) -> dict[str, Any]:
    """Online changes into nets of each size (the first from the smallest net running), the
    scan waiting busy (`softplc run --busy-wait`, what a virtual machine needs: a sleeping
    virtual CPU is woken late); then the same changes with the scan sleeping (key
    `sleeping`), each beside its own empty-loop floor. The busy scan is pinned to the last
    CPU (when there are two or more), everything else kept off it (key `scan_cpu`). Key
    `missed_scans` (max over sizes, busy). `split_up_to`: sizes up to this also get
    split_cost_ms (quick: 1,000; full: all), which compiles each net once more here."""
    split_limit = split_up_to if split_up_to is not None else (1000 if quick else max(sizes))
    counts = repeats or {n: (3 if n <= 1000 else 1) if quick else (10 if n <= 1000 else 3)
                         for n in sizes}
    period_ns = period_ms * 1_000_000
    load_before = os.getloadavg()
    busy = _session(True, sizes, counts, period_ns, settle_s, timeout_s, split_limit, progress)
    sleeping = _session(False, sizes, counts, period_ns, settle_s, timeout_s, 0, progress)
    for v in sleeping["by_size"].values():
        v.pop("split", None)
    return {"period_ms": period_ms, "via": "HTTP API POST /api/v1/program?online=true",
            "load_average_1m": [load_before[0], os.getloadavg()[0]], **busy,
            "sleeping": {k: sleeping[k] for k in ("floor", "by_size", "missed_scans",
                                                  "missed_scans_before", "scan_cpu")}}


def _worst(values: Iterable[int | None]) -> int | None:
    known = [v for v in values if v is not None]
    return max(known) if known else None
