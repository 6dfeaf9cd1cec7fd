"""The node's session in-process against Mosquitto (TCK SendDataTest's seq rule): seq 0 in the
NBIRTH, then +1 in every NDATA over more than 256 messages, 255 wrapping to 0, read from the
raw protobuf by Tahu JS; a clean close publishes the NDEATH with the session's bdSeq and no
seq; the next session's bdSeq is the next one."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from softplc.sparkplug.config import SparkplugConfig
from softplc.sparkplug.node import EdgeNode
from tests.sparkplug.conftest import Broker, Host, Tahu

pytestmark = pytest.mark.slow  # a real broker; about a second


def _run_until(node: EdgeNode, done: Callable[[], bool], timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():
        assert time.monotonic() < deadline, "the node did not get there in time"
        node.step(0.002)


def test_seq_wraps_and_a_clean_close_sends_ndeath(tmp_path: Path, tahu: Tahu,
                                                   mosquitto: Callable[..., Broker],
                                                   host: Callable[..., Host]) -> None:
    broker = mosquitto()
    h = host(broker.port)
    scans = iter(range(10**9))

    def read() -> tuple[dict[str, Any], None]:  # a PLC whose scan count moves at every read
        return {"state": "RUNNING", "program": "p", "program_hash": "ab",
                "scan_count": next(scans), "symbols": {}}, None

    config = SparkplugConfig("127.0.0.1", broker.port, "g", "n1", state_dir=str(tmp_path),
                             interval_s=0.0)
    node = EdgeNode(config, read, lambda report, metric: None)
    try:
        _run_until(node, lambda: len(h.since(0, "NDATA")) >= 300)
    finally:
        node.close()
    death = h.wait("NDEATH")[1]
    messages = [m for _, m in h.since(0, "NBIRTH")] + [m for _, m in h.since(0, "NDATA")]
    messages.sort(key=lambda m: h.messages.index(m))
    seqs = [int(d["raw"]["seq"]) for d in tahu.decode([m.payload for m in messages])]
    assert seqs[:1] == [0] and len(seqs) >= 301
    assert seqs == [i % 256 for i in range(len(seqs))]
    dead = tahu.decode([death.payload])[0]
    assert "seq" not in dead["raw"] and int(dead["payload"]["metrics"][0]["value"]) == 0
    again = EdgeNode(config, read, lambda report, metric: None)
    mark = h.count()
    try:
        _run_until(again, lambda: bool(h.since(mark, "NBIRTH")))
    finally:
        again.close()
    birth = tahu.decode([h.wait("NBIRTH", mark)[1].payload])[0]
    assert [int(m["value"]) for m in birth["payload"]["metrics"] if m["name"] == "bdSeq"] == [1]
