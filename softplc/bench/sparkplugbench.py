"""Benchmark section `sparkplug` (issue 41; on request: `softplc bench --only sparkplug`, it
needs Debian's `mosquitto`): a fleet of NODES `softplc run programs/transport.yaml` edge
nodes on one Mosquitto, each also a Modbus slave.

Keys: `latency_ms` (an HMI's Modbus write of `hold` to the NDATA that carries it at a
subscriber, p50/p99) against `modbus_poll_ms` (the same write to a Modbus read that shows it,
polled every POLL_S by the same client, same trials); `metrics_per_s` in total and per node
(`PLC/Scan Count` changes every scan: a metric in every NDATA at the node's interval);
`cpu_percent_per_1000_metrics_s` (the Sparkplug processes' CPU over the window, per 1,000
metrics/s); `p99_late_with_us` / `p99_late_without_us` (the median over the nodes of the
scan's p99 lateness, Modbus status block, each over a whole statistics window; "without":
the same PLCs with their Sparkplug processes SIGSTOPped, same run) and their ratio;
`broker_gone` (the Sparkplug processes' RSS before and after the broker is away
BROKER_GONE_S, and how long until every node was born again once it is back).
Owns: the broker, the fleet, the subscriber. Does not know: the node's internals.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Final

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion
from pymodbus.client import ModbusTcpClient

from softplc.bench.live import ROOT, end_run, free_port, rss_kib
from softplc.bench.measure import Progress
from softplc.core.image import ImageSizes
from softplc.sparkplug import codec

NODES: Final = 10
INTERVAL_S: Final = "0.02"  # --sparkplug-interval of the fleet
POLL_S: Final = 0.002
HOLD_COIL: Final = ImageSizes().bits  # %MX0.0: the first memory coil
STATS_WINDOW_S: Final = 12.0  # > the scan statistics' window (1,000 scans at 10 ms)
BROKER_GONE_S: Final = 60.0
# The Modbus status block as an HMI reads it (docs/modbus.md): input registers from the image's
# word count; the scan's p99 lateness, u32 high word first, at offset 8.
P99_LATE_REGISTER: Final = ImageSizes().words + 8


class Subscriber:
    """Every NDATA/NBIRTH of the fleet, with its arrival time."""

    def __init__(self, port: int) -> None:
        self.lock = threading.Lock()
        self.births: dict[str, int] = {}  # node -> births seen
        self.hold_alias: dict[str, int] = {}
        self.hold_seen: dict[str, list[tuple[float, bool]]] = {}
        self.metrics = 0
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id="bench-host")
        self.subscribed = threading.Event()
        self.client.on_connect = lambda c, u, f, r, p: c.subscribe("spBv1.0/bench/#")
        self.client.on_subscribe = lambda c, u, m, r, p: self.subscribed.set()
        self.client.on_message = self._message
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        if not self.subscribed.wait(30.0):
            raise RuntimeError("the bench's subscriber could not subscribe")

    def _message(self, client: Any, userdata: Any, message: mqtt.MQTTMessage) -> None:
        now = time.monotonic()
        _, _, kind, node = message.topic.split("/")[:4]
        payload = codec.decode(bytes(message.payload))
        with self.lock:
            if kind == "NBIRTH":
                self.births[node] = self.births.get(node, 0) + 1
                self.hold_alias[node] = next(m.alias for m in payload.metrics
                                             if m.name == "hold" and m.alias is not None)
            elif kind == "NDATA":
                self.metrics += len(payload.metrics)
                alias = self.hold_alias.get(node)
                for metric in payload.metrics:
                    if metric.alias == alias:
                        self.hold_seen.setdefault(node, []).append((now, bool(metric.value)))

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def _broker(port: int, where: Path, n: int = 0) -> subprocess.Popen[bytes]:
    """Mosquitto on `port`; its connection notices in where/broker-N.log."""
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    conf = where / "m.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
                    "user root\nlog_dest stderr\nlog_type notice\n")
    with (where / f"broker-{n}.log").open("wb") as log:
        return subprocess.Popen([binary, "-c", str(conf)], stdout=subprocess.DEVNULL,
                                stderr=log)


def _sparkplug_pids(supervisor: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            comm = (entry / "comm").read_text().strip()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == supervisor and \
                comm.startswith("softplc-sparkp"):
            found.append(int(entry.name))
    return found


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0


def _cpu_s(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _p99_late(port: int) -> int:
    with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as client:
        regs = client.read_input_registers(P99_LATE_REGISTER, count=2).registers
    return int(regs[0] << 16 | regs[1])


def _quantiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {"p50": round(statistics.median(ordered), 2),
            "p99": round(ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))], 2),
            "n": len(ordered)}


def _wait(predicate: Any, timeout_s: float, what: str) -> float:
    start = time.monotonic()
    while not predicate():
        if time.monotonic() - start > timeout_s:
            raise RuntimeError(f"{what} not within {timeout_s:g} s")
        time.sleep(0.05)
    return time.monotonic() - start


def run(quick: bool, progress: Progress) -> dict[str, Any]:
    if not (shutil.which("mosquitto") or Path("/usr/sbin/mosquitto").exists()):
        raise RuntimeError("mosquitto is not installed (apt-get install mosquitto)")
    trials = 12 if quick else 40
    gone_s = 10.0 if quick else BROKER_GONE_S
    with tempfile.TemporaryDirectory(prefix="softplc-spbench-") as tmp:
        where = Path(tmp)
        port = free_port()
        brokers = [_broker(port, where)]
        plcs: list[tuple[subprocess.Popen[str], int]] = []
        sub: Subscriber | None = None
        try:
            time.sleep(0.3)
            sub = Subscriber(port)
            for i in range(NODES):
                mb = free_port()
                state = where / f"plc{i}"
                state.mkdir()
                args = [sys.executable, "-m", "softplc.cli", "run", "programs/transport.yaml",
                        "--start", "--modbus", f"127.0.0.1:{mb}", "--api", "off",
                        "--opcua", "off", "--state-dir", str(state), "--quiet",
                        "--sparkplug", f"mqtt://127.0.0.1:{port}/bench/plc{i}",
                        "--sparkplug-interval", INTERVAL_S]
                log = (state / "run.log").open("w")
                plcs.append((subprocess.Popen(args, cwd=ROOT, stdout=log,
                                              stderr=subprocess.STDOUT, text=True,
                                              start_new_session=True), mb))
                log.close()
            progress(f"sparkplug: {NODES} nodes starting")
            s = sub
            _wait(lambda: len(s.births) == NODES, 180.0, "every NBIRTH")
            _wait(lambda: all(_listening(mb) for _, mb in plcs), 180.0, "every Modbus slave")
            time.sleep(2.0)
            result: dict[str, Any] = {"nodes": NODES, "interval_s": float(INTERVAL_S)}
            result.update(_latency(sub, plcs, trials, progress))
            pids = [p for proc, _ in plcs for p in _sparkplug_pids(proc.pid)]
            result.update(_throughput(sub, pids, 5.0 if quick else 10.0))
            result.update(_lateness(plcs, pids, progress))
            result["broker_gone"] = _broker_gone(sub, brokers, port, where, pids, gone_s,
                                                 progress)
            return result
        finally:
            if sub is not None:
                sub.close()
            for proc, _ in plcs:
                end_run(proc)
            for broker in brokers:
                broker.terminate()
                broker.wait(5)


def _latency(sub: Subscriber, plcs: list[tuple[subprocess.Popen[str], int]], trials: int,
             progress: Progress) -> dict[str, Any]:
    sparkplug: list[float] = []
    modbus: list[float] = []
    for trial in range(trials):
        index = trial % len(plcs)
        node, port = f"plc{index}", plcs[index][1]
        with ModbusTcpClient("127.0.0.1", port=port, timeout=5) as client:
            value = not bool(client.read_coils(HOLD_COIL, count=1).bits[0])
            with sub.lock:
                seen_before = len(sub.hold_seen.get(node, []))
            start = time.monotonic()
            client.write_coil(HOLD_COIL, value)
            while bool(client.read_coils(HOLD_COIL, count=1).bits[0]) != value:
                time.sleep(POLL_S)
            modbus.append((time.monotonic() - start) * 1000)

        def arrived(node: str = node, value: bool = value, n: int = seen_before) -> bool:
            with sub.lock:
                return any(v == value for _, v in sub.hold_seen.get(node, [])[n:])

        _wait(arrived, 10.0, "the NDATA of a write")
        with sub.lock:
            at = next(t for t, v in sub.hold_seen[node][seen_before:] if v == value)
        sparkplug.append((at - start) * 1000)
    progress(f"sparkplug: {trials} write trials")
    lat, poll = _quantiles(sparkplug), _quantiles(modbus)
    return {"latency_ms": lat, "modbus_poll_ms": poll,
            "latency_p50_over_modbus": round(lat["p50"] / poll["p50"], 2) if poll["p50"] else None}


def _throughput(sub: Subscriber, pids: list[int], window_s: float) -> dict[str, Any]:
    with sub.lock:
        before = sub.metrics
    cpu0 = sum(_cpu_s(p) for p in pids)
    time.sleep(window_s)
    cpu1 = sum(_cpu_s(p) for p in pids)
    with sub.lock:
        rate = (sub.metrics - before) / window_s
    cpu_percent = (cpu1 - cpu0) / window_s * 100
    return {"metrics_per_s": round(rate, 1), "metrics_per_s_per_node": round(rate / NODES, 1),
            "cpu_percent_all_nodes": round(cpu_percent, 1),
            "cpu_percent_per_1000_metrics_s": round(cpu_percent / (rate / 1000), 2)
            if rate else None}


def _lateness(plcs: list[tuple[subprocess.Popen[str], int]], pids: list[int],
              progress: Progress) -> dict[str, Any]:
    time.sleep(STATS_WINDOW_S)
    with_sp = statistics.median(_p99_late(port) for _, port in plcs)
    for pid in pids:
        os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(STATS_WINDOW_S)
        without = statistics.median(_p99_late(port) for _, port in plcs)
    finally:
        for pid in pids:
            os.kill(pid, signal.SIGCONT)
    progress("sparkplug: scan lateness with and without")
    return {"p99_late_with_us": with_sp, "p99_late_without_us": without,
            "p99_late_ratio": round(with_sp / without, 2) if without else None}


def _broker_gone(sub: Subscriber, brokers: list[subprocess.Popen[bytes]], port: int,
                 where: Path,
                 pids: list[int], gone_s: float, progress: Progress) -> dict[str, Any]:
    rss_before = sum(rss_kib(p) for p in pids)
    with sub.lock:
        births = dict(sub.births)
    brokers[0].terminate()
    brokers[0].wait(5)
    peak = rss_before
    end = time.monotonic() + gone_s
    while time.monotonic() < end:
        peak = max(peak, sum(rss_kib(p) for p in pids))
        time.sleep(1.0)
    rss_gone = sum(rss_kib(p) for p in pids)
    start = time.monotonic()
    brokers.append(_broker(port, where, 1))  # run() stops it
    log = where / "broker-1.log"
    nodes = [f"softplc-bench-{n}" for n in births]

    def connected() -> bool:
        text = log.read_text(errors="replace") if log.exists() else ""
        return all(f"as {n} " in text for n in nodes)

    _wait(connected, 120.0, "every node connected again")
    reconnected = time.monotonic() - start
    time.sleep(0.5)
    fresh = Subscriber(port)  # a host that came back after the nodes' births: asks them
    try:
        deadline = time.monotonic() + 60.0
        while len(fresh.births) < len(births):  # as a host does: Rebirth for the missing
            if time.monotonic() > deadline:
                raise RuntimeError(f"nodes {sorted(set(births) - set(fresh.births))} not "
                                   "born again within 60 s")
            for node in set(births) - set(fresh.births):
                fresh.client.publish(f"spBv1.0/bench/NCMD/{node}", codec.encode(
                    codec.Payload(int(time.time() * 1000), (codec.Metric(
                        "Node Control/Rebirth", codec.BOOLEAN, True),))))
            time.sleep(3.0)
    finally:
        fresh.close()
    progress(f"sparkplug: broker away {gone_s:g} s")
    return {"away_s": gone_s, "rss_kib_before": rss_before, "rss_kib_peak": peak,
            "rss_kib_after": rss_gone, "all_connected_again_s": round(reconnected, 1)}
