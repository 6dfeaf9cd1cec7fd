"""Primary host awareness (Sparkplug 3.0 STATE, JSON): with --sparkplug-primary-host the node
births only after the host's STATE online; a STATE offline with a newer timestamp makes it
publish NDEATH and start a new session (the next bdSeq) that waits again; a stale offline
changes nothing; the host back online gets a new birth."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.sparkplug.conftest import Broker, Host, Tahu, metrics_of, start_plc, stop_plc
from tests.support import wait_until

STATE = "spBv1.0/STATE/scada1"

pytestmark = pytest.mark.slow  # real softplc runs against a real broker


def _state(online: bool, stamp: int) -> bytes:
    return json.dumps({"online": online, "timestamp": stamp}).encode()


def test_births_follow_the_primary_host(tmp_path: Path, tahu: Tahu,
                                        mosquitto: Callable[..., Broker],
                                        host: Callable[..., Host]) -> None:
    broker = mosquitto()
    h = host(broker.port)
    state = tmp_path / "state"
    plc = start_plc(state, f"mqtt://127.0.0.1:{broker.port}/plant/tank1",
                    "--sparkplug-primary-host", "scada1")
    try:
        # the node subscribed to the host's STATE (and so waits for it) ...
        assert wait_until(lambda: "spBv1.0/STATE/scada1 (QoS 1)" in broker.log_text(), 20.0)
        assert not h.since(0, "NBIRTH")
        # ... a stale STATE of another host id changes nothing; the host's online births
        h.send("spBv1.0/STATE/other", _state(True, 5000), qos=1, retain=True)
        mark = h.count()
        h.send(STATE, _state(True, 1000), qos=1, retain=True)
        index, birth = h.wait("NBIRTH")
        assert index >= mark
        assert int(metrics_of(tahu.decode([birth.payload])[0])["bdSeq"]["value"]) == 0
        # an offline older than the online it saw: nothing (a Rebirth sent after it is
        # answered by a birth in the same session, with no death between)
        mark = h.count()
        h.send(STATE, _state(False, 999), qos=1, retain=True)
        h.send("spBv1.0/plant/NCMD/tank1", tahu.encode({"timestamp": 1, "metrics": [
            {"name": "Node Control/Rebirth", "type": "Boolean", "value": True}]}))
        _, again = h.wait("NBIRTH", mark)
        assert int(metrics_of(tahu.decode([again.payload])[0])["bdSeq"]["value"]) == 0
        assert not h.since(0, "NDEATH")
        # the host goes offline: NDEATH (the birth's bdSeq), a new session that waits
        mark = h.count()
        h.send(STATE, _state(False, 2000), qos=1, retain=True)
        index, death = h.wait("NDEATH", mark)
        dead = tahu.decode([death.payload])[0]["payload"]["metrics"][0]
        assert int(dead["value"]) == 0
        assert not h.since(mark, "NBIRTH")
        # back online: a new birth, the next bdSeq
        assert wait_until(lambda: broker.log_text().count("as softplc-plant-tank1") >= 2, 20.0)
        h.send(STATE, _state(True, 3000), qos=1, retain=True)
        _, reborn = h.wait("NBIRTH", index)
        assert int(metrics_of(tahu.decode([reborn.payload])[0])["bdSeq"]["value"]) == 1
    finally:
        stop_plc(plc)
