"""Issue 41's DONE-WHEN: `softplc run --sparkplug` against Mosquitto, every payload decoded by
Eclipse Tahu JS. NBIRTH (seq 0, bdSeq, Rebirth, every symbol typed, with its properties),
NDATA by alias, an NCMD write seen in the process image (HTTP API) and in the audit trail, a
refused write answered in the status metric and audited, Rebirth (a full NBIRTH, same bdSeq,
no new CONNECT), SIGKILL of the whole PLC (the broker's Will NDEATH with the birth's bdSeq),
and a restart (the next bdSeq). The broker's log pins the MQTT-level rules (Will QoS 1 not
retained, clean session, NCMD subscribed at QoS 1, births and data QoS 0 not retained)."""

from __future__ import annotations

import json
import re
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.sparkplug.conftest import (
    Broker,
    Host,
    Tahu,
    kill_plc,
    metrics_of,
    start_plc,
    stop_plc,
)
from tests.support import free_port, wait_until

NODE = "plant/tank1"
TOPIC = "spBv1.0/plant/%s/tank1"

pytestmark = pytest.mark.slow  # real softplc runs against a real broker


def _symbol(api_port: int, name: str) -> Any:
    url = f"http://127.0.0.1:{api_port}/api/v1/symbols/{name}"
    try:
        with urllib.request.urlopen(url, timeout=5) as reply:
            return json.load(reply)["value"]
    except urllib.error.URLError:  # the HTTP process still starting
        return None


def _audit(state_dir: Path) -> list[dict[str, Any]]:
    path = state_dir / "audit.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines()
            if '"sparkplug"' in line]


def _status_metric(tahu: Tahu, host: Host, start: int, alias: int, want: str) -> str:
    """The Command Status metric's value in an NDATA after `start` that contains `want`."""
    seen: list[str] = []

    def found() -> bool:
        payloads = [m.payload for _, m in host.since(start, "NDATA")]
        for decoded in tahu.decode(payloads) if payloads else []:
            for metric in decoded["raw"].get("metrics", []):
                if int(metric.get("alias", -1)) == alias and "stringValue" in metric:
                    seen.append(metric["stringValue"])
        return any(want in s for s in seen)

    assert wait_until(found, 30.0, 0.3), f"no status {want!r} in NDATA; saw {seen}"
    return next(s for s in seen if want in s)


def test_edge_node_against_mosquitto(tmp_path: Path, tahu: Tahu,
                                     mosquitto: Callable[..., Broker],
                                     host: Callable[..., Host]) -> None:
    broker = mosquitto()
    h = host(broker.port)
    api = free_port()
    state = tmp_path / "state"
    url = f"mqtt://127.0.0.1:{broker.port}/{NODE}"
    plc = start_plc(state, url, "--api", f"127.0.0.1:{api}", "--sparkplug-role", "operator",
                    "--sparkplug-interval", "0.05")
    try:
        # -- NBIRTH, decoded by Tahu JS --------------------------------------------------------
        _, birth = h.wait("NBIRTH")
        assert birth.topic == TOPIC % "NBIRTH" and birth.qos == 0 and not birth.retain
        decoded = tahu.decode([birth.payload])[0]
        assert int(decoded["payload"]["seq"]) == 0 and int(decoded["payload"]["timestamp"]) > 0
        assert h.messages[0].topic == TOPIC % "NBIRTH"  # the node's first message
        metrics = metrics_of(decoded)
        assert metrics["bdSeq"]["type"] == "Int64" and int(metrics["bdSeq"]["value"]) == 0
        rebirth = metrics["Node Control/Rebirth"]
        assert rebirth["type"] == "Boolean" and rebirth["value"] is False
        assert "alias" not in rebirth
        types = {n: m["type"] for n, m in metrics.items()}
        assert types["level"] == "Double"  # scaled: engineering units
        assert types["high_switch"] == "Boolean" and types["batches"] == "Int32"
        assert types["fill_to"] == "Float" and types["PLC/State"] == "String"
        assert types["PLC/Scan Count"] == "UInt64"
        assert metrics["fill_to"]["value"] == 80.0
        assert metrics["PLC/Program"]["value"] == "tank"
        level_props = {k: v["value"] for k, v in metrics["level"]["properties"].items()}
        assert level_props == {"readOnly": True, "engUnit": "%", "engLow": 0.0, "engHigh": 100.0}
        assert metrics["fill_to"]["properties"]["readOnly"]["value"] is False
        assert all("timestamp" in m for m in metrics.values())
        aliases = [int(m["alias"]) for n, m in metrics.items() if "alias" in m]
        assert len(aliases) == len(set(aliases)) == len(metrics) - 2  # not bdSeq nor Rebirth
        status_alias = int(metrics["Node Control/Command Status"]["alias"])

        # -- NDATA: by alias only, seq going on ------------------------------------------------
        first, data = h.wait("NDATA")
        raw = tahu.decode([data.payload])[0]["raw"]
        assert int(raw["seq"]) == 1 and data.qos == 0 and not data.retain
        assert all("name" not in m and "datatype" not in m and "alias" in m
                   for m in raw["metrics"])

        # -- NCMD write (encoded by Tahu JS): the process image and the audit trail ------------
        ncmd = tahu.encode({"timestamp": 1, "metrics": [
            {"name": "fill_to", "type": "Float", "value": 55.5}]})
        h.send(TOPIC % "NCMD", ncmd)
        assert wait_until(lambda: _symbol(api, "fill_to") == 55.5, 30.0, 0.05)
        assert wait_until(lambda: any(r["action"] == "write" and r["outcome"] == "queued"
                                      for r in _audit(state)), 10.0, 0.05)
        record = next(r for r in _audit(state) if r["outcome"] == "queued")
        assert record["detail"]["metric"] == "fill_to"
        assert float(record["detail"]["value"]) == 55.5  # the trail keeps floats as text
        assert record["role"] == "operator"
        _status_metric(tahu, h, first, status_alias, "write fill_to: queued")

        # -- a refused write (an input): status metric and audit -------------------------------
        mark = h.count()
        h.send(TOPIC % "NCMD", tahu.encode({"timestamp": 2, "metrics": [
            {"name": "high_switch", "type": "Boolean", "value": True}]}))
        _status_metric(tahu, h, mark, status_alias, "write high_switch: refused")
        assert wait_until(lambda: any(r["detail"]["metric"] == "high_switch"
                                      and r["outcome"] == "refused" for r in _audit(state)))
        h.send(TOPIC % "NCMD", tahu.encode({"timestamp": 2, "metrics": [
            {"name": "PLC/State", "type": "String", "value": "RUNNING"}]}))
        _status_metric(tahu, h, mark, status_alias, "PLC/State: refused (PLC/State is read only)")
        # program commands are off by default: refused and audited
        h.send(TOPIC % "NCMD", tahu.encode({"timestamp": 3, "metrics": [
            {"name": "Node Control/Command", "type": "String", "value": "stop"}]}))
        _status_metric(tahu, h, mark, status_alias, "stop Node Control/Command: refused")

        # -- Rebirth: a full NBIRTH, seq 0, same bdSeq, no new CONNECT -------------------------
        mark = h.count()
        connects = broker.log_text().count("as softplc-plant-tank1")
        h.send(TOPIC % "NCMD", tahu.encode({"timestamp": 4, "metrics": [
            {"name": "Node Control/Rebirth", "type": "Boolean", "value": True}]}))
        _, again = h.wait("NBIRTH", mark)
        re_decoded = tahu.decode([again.payload])[0]
        assert int(re_decoded["payload"]["seq"]) == 0
        assert set(metrics_of(re_decoded)) == set(metrics)
        assert int(metrics_of(re_decoded)["bdSeq"]["value"]) == 0
        assert broker.log_text().count("as softplc-plant-tank1") == connects

        # -- SIGKILL: the broker's Will NDEATH with the birth's bdSeq --------------------------
        mark = h.count()
        kill_plc(plc)
        _, death = h.wait("NDEATH", mark)
        assert death.qos == 1 and not death.retain
        dead = tahu.decode([death.payload])[0]
        assert [m["name"] for m in dead["payload"]["metrics"]] == ["bdSeq"]
        assert int(dead["payload"]["metrics"][0]["value"]) == 0
        assert "seq" not in dead["raw"]

        # -- restart: the next bdSeq -----------------------------------------------------------
        mark = h.count()
        plc = start_plc(state, url)
        _, reborn = h.wait("NBIRTH", mark)
        assert int(metrics_of(tahu.decode([reborn.payload])[0])["bdSeq"]["value"]) == 1
        # a clean stop: NDEATH (same bdSeq) before DISCONNECT
        mark = h.count()
        stop_plc(plc)
        _, bye = h.wait("NDEATH", mark)
        assert int(tahu.decode([bye.payload])[0]["payload"]["metrics"][0]["value"]) == 1
    finally:
        stop_plc(plc)
    log = broker.log_text()
    assert re.search(r"as softplc-plant-tank1 \(p2, c1, k\d+\)", log), log[-3000:]
    assert "Will message specified (" in log and re.search(r"Will message specified \(\d+ "
                                                           r"bytes\) \(r0, q1\)", log)
    assert re.search(r"spBv1\.0/plant/NCMD/tank1 \(QoS 1\)", log)
    births = re.findall(r"Received PUBLISH from softplc-plant-tank1 \((d0, q\d, r\d)[^']*"
                        r"'spBv1\.0/plant/(NBIRTH|NDATA)/tank1'", log)
    assert births and {flags for flags, _ in births} == {"d0, q0, r0"}
