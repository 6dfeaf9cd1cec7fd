"""The Sparkplug B edge node's MQTT session: connect with the NDEATH Will, births, report by
exception, rebirth, primary host STATE, death, reconnect.

Owns: one paho-mqtt client per CONNECT (MQTT 3.1.1, clean session) driven from one thread
(`step`: no paho thread, no lock); bdSeq, persisted in STATE_DIR/sparkplug/bdseq before each
CONNECT is used, so the next birth after a restart or a kill -9 has the next one (spec 5.4:
0..255, wrapping); seq (NBIRTH 0, then +1 mod 256 over every NDATA); the NDEATH Will (QoS 1,
not retained) and the same NDEATH published before an intentional DISCONNECT; births after
the NCMD subscription is acknowledged (and the primary host's STATE online, when one is
configured); a new birth when the program changes (its metrics changed) or a host asks
(Node Control/Rebirth); NDATA at most every `interval_s`, and none while the socket has not
taken the last one (the unsent changes wait: memory stays bounded while the broker is slow or
gone, and nothing is stored to forward); reconnecting with backoff, each CONNECT a new bdSeq.
Does not know: the channel, roles, the audit trail (door.py), payload bytes (codec.py).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Final

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode

from softplc.core.image import ProcessImage
from softplc.sparkplug import codec
from softplc.sparkplug.codec import DecodeError, Metric, Payload
from softplc.sparkplug.config import SparkplugConfig
from softplc.sparkplug.metrics import BDSEQ, COMMAND, REBIRTH, Report

log = logging.getLogger(__name__)

NAMESPACE: Final = "spBv1.0"
BACKOFF_S: Final = (0.5, 1.0, 2.0, 5.0)
MAX_QUEUED: Final = 64  # QoS 1 messages paho may hold (the NDEATH); QoS 0: see step()
NDEATH_WAIT_S: Final = 1.0  # an intentional stop waits this long for the NDEATH to go
Reading = tuple[Mapping[str, Any], ProcessImage | None]  # (status board, latest image)


def now_ms() -> int:
    return int(time.time() * 1000)


class BdSeq:
    """The birth/death sequence number of each CONNECT, kept in a file of the state dir."""

    def __init__(self, state_dir: str) -> None:
        self.path = Path(state_dir) / "sparkplug" / "bdseq"
        self._used: int | None = None  # the last one this process used (if the file fails)

    def last(self) -> int | None:
        if self._used is not None:
            return self._used
        try:
            number = int(self.path.read_text().strip())
        except (OSError, ValueError):
            return None
        return number if 0 <= number <= 255 else None

    def next(self) -> int:
        last = self.last()
        return 0 if last is None else (last + 1) % 256

    def keep(self, number: int) -> None:
        """`number` is used from now on: kept in memory, then in the file (OSError if not)."""
        self._used = number
        self.path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        tmp = self.path.with_suffix(".tmp")
        with tmp.open("w") as out:
            out.write(f"{number}\n")
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, self.path)


class EdgeNode:
    """One edge node. `read()` gives the status board and the latest image; `command(name,
    alias, metric)` hands a host's NCMD metric (not Rebirth) to the door."""

    def __init__(self, config: SparkplugConfig, read: Callable[[], Reading],
                 command: Callable[[Report | None, Metric], None]) -> None:
        self.config = config
        self._read = read
        self._command = command
        base = f"{NAMESPACE}/{config.group}/%s/{config.node}"
        self.topic = {kind: base % kind for kind in ("NBIRTH", "NDEATH", "NDATA", "NCMD")}
        self.state_topic = f"{NAMESPACE}/STATE/{config.primary_host}" \
            if config.primary_host else None
        self.bdseq = BdSeq(config.state_dir)
        self.client: mqtt.Client | None = None
        self.current_bdseq = -1
        self.seq = 0
        self.connected = self.subscribed = self.born = False
        self.host_online = config.primary_host is None
        self.host_ts = -1  # the last STATE timestamp taken from the primary host
        self.rebirth = self.host_left = False
        self.report: Report | None = None
        self.next_try_s = 0.0
        self.failures = 0
        self.last_data_s = 0.0
        self.keep_failed = False
        self.counts = {"births": 0, "data": 0, "skipped": 0, "commands": 0, "connects": 0}

    # -- the loop ---------------------------------------------------------------------------

    def step(self, timeout_s: float) -> None:
        """Connect when due, let paho read and write for up to `timeout_s`, then birth or
        report what changed."""
        if self.client is None:
            if time.monotonic() >= self.next_try_s:
                self._connect()
            else:
                time.sleep(min(timeout_s, max(0.0, self.next_try_s - time.monotonic())))
            return
        self.client.loop(timeout=timeout_s)
        if self.host_left:
            self.host_left = False
            self.close()
            self._retry(f"primary host {self.config.primary_host} is offline")
            self.next_try_s = time.monotonic()
            return
        if self.client is None or not (self.connected and self.subscribed and self.host_online):
            return
        due = time.monotonic() - self.last_data_s >= self.config.interval_s
        if self.born and not self.rebirth and not due:
            return
        if self.born and self.client.want_write():  # the last message still waits for the
            self.counts["skipped"] += 1  # socket: no NDATA, and no NBIRTH per Rebirth asked
            return  # meanwhile either (paho's queue of QoS 0 messages has no bound)
        board, image = self._read()
        changed_program = self.report is not None and \
            self.report.document.get("program_hash") != board.get("program_hash")
        if not self.born or self.rebirth or changed_program:
            self._birth(board, image)
        else:
            self._data(board, image)

    def close(self) -> None:
        """An intentional stop: NDEATH with this connection's bdSeq, then DISCONNECT."""
        client = self.client
        if client is None or not self.connected:
            return
        info = client.publish(self.topic["NDEATH"], self._death(), qos=1, retain=False)
        deadline = time.monotonic() + NDEATH_WAIT_S
        while not info.is_published() and time.monotonic() < deadline and self.connected:
            client.loop(timeout=0.05)
        self.client = None  # its disconnect is ours, not one to retry
        client.disconnect()
        with contextlib.suppress(Exception):
            client.loop(timeout=0.05)

    # -- the session ------------------------------------------------------------------------

    def _death(self) -> bytes:
        return codec.encode(Payload(now_ms(), (Metric(BDSEQ, codec.INT64,
                                                      self.current_bdseq),)))

    def _connect(self) -> None:
        config = self.config
        bdseq = self.bdseq.next()
        self.current_bdseq = bdseq
        client = mqtt.Client(CallbackAPIVersion.VERSION2,
                             client_id=f"softplc-{config.group}-{config.node}",
                             clean_session=True, protocol=mqtt.MQTTv311,
                             reconnect_on_failure=False)
        client.will_set(self.topic["NDEATH"], self._death(), qos=1, retain=False)
        if config.user is not None:
            client.username_pw_set(config.user, config.password)
        if config.tls:
            client.tls_set(ca_certs=config.ca_file)
        client.max_queued_messages_set(MAX_QUEUED)
        client.on_connect, client.on_subscribe = self._on_connect, self._on_subscribe
        client.on_disconnect, client.on_message = self._on_disconnect, self._on_message
        self.connected = self.subscribed = self.born = False
        self.host_online = config.primary_host is None
        try:  # kept before the CONNECT that carries it goes out (a kill -9 right after it
            self.bdseq.keep(bdseq)  # must not give the next session the same bdSeq)
        except OSError as exc:  # a full or read-only state dir: report on, say so once
            if not self.keep_failed:
                log.error("Sparkplug: bdSeq not kept in %s (%s): after a restart, hosts may "
                          "see a bdSeq again", self.bdseq.path, exc)
            self.keep_failed = True
        try:
            client.connect(config.host, config.port, keepalive=config.keepalive_s)
        except (OSError, ValueError) as exc:
            self._retry(f"cannot connect to {config.host}:{config.port}: {exc}")
            return
        self.counts["connects"] += 1
        self.client = client

    def _retry(self, why: str) -> None:
        delay = BACKOFF_S[min(self.failures, len(BACKOFF_S) - 1)]
        if self.failures == 0 or (delay == BACKOFF_S[-1] and self.failures % 12 == 0):
            log.warning("Sparkplug: %s; trying again in %g s", why, delay)
        self.failures += 1
        self.next_try_s = time.monotonic() + delay
        self.client = None
        self.connected = self.subscribed = self.born = False

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                    properties: Any) -> None:
        if reason.is_failure:
            client.disconnect()
            self._retry(f"the broker refused the connection: {reason}")
            return
        self.connected, self.failures = True, 0
        topics = [(self.topic["NCMD"], 1)]
        if self.state_topic:
            topics.append((self.state_topic, 1))
        client.subscribe(topics)

    def _on_subscribe(self, client: mqtt.Client, userdata: Any, mid: int, reasons: Any,
                      properties: Any) -> None:
        self.subscribed = True

    def _on_disconnect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any,
                       properties: Any) -> None:
        if client is self.client:
            self._retry(f"disconnected from {self.config.host}:{self.config.port} ({reason})")

    def _on_message(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage
                    ) -> None:
        if message.topic == self.state_topic:
            self._state(bytes(message.payload))  # paho 2.2 types it bytes | bytearray
            return
        try:
            payload = codec.decode(bytes(message.payload))
        except DecodeError as exc:
            log.warning("Sparkplug: an NCMD that is no Sparkplug B payload ignored: %s", exc)
            return
        for metric in payload.metrics:
            if metric.name == REBIRTH:
                self.rebirth = self.rebirth or metric.value is True
            else:  # also before any birth (None): the door refuses it, audited
                self.counts["commands"] += 1
                self._command(self.report, metric)

    def _state(self, raw: bytes) -> None:
        """The primary host's STATE (3.0: JSON {"online", "timestamp"}; the older plain
        ONLINE/OFFLINE is taken too, without a timestamp)."""
        try:
            text = raw.decode("utf-8").strip()
            doc = json.loads(text) if text.startswith("{") else \
                {"online": text == "ONLINE", "timestamp": self.host_ts}
            online, stamp = doc["online"], int(doc["timestamp"])
            if not isinstance(online, bool):  # {"online": "false"} is no boolean
                raise TypeError(online)
        except (UnicodeDecodeError, ValueError, KeyError, TypeError, OverflowError,
                RecursionError):  # e.g. "timestamp": Infinity, or nested 10**5 deep
            log.warning("Sparkplug: a STATE message that is not {online, timestamp} ignored")
            return
        if stamp < self.host_ts:
            return  # an older message (a stale Will): nothing changes
        self.host_ts = stamp
        if online:
            self.host_online = True
            return
        if self.host_online:  # the host went away: death, and a new session (new bdSeq)
            self.host_left = True  # whose births wait for it again (step(), out of paho's
            self.host_online = False  # callback)

    # -- births and data --------------------------------------------------------------------

    def _publish(self, kind: str, metrics: list[Metric]) -> bool:
        assert self.client is not None
        payload = codec.encode(Payload(now_ms(), tuple(metrics), self.seq))
        info = self.client.publish(self.topic[kind], payload, qos=0, retain=False)
        if info.rc != MQTTErrorCode.MQTT_ERR_SUCCESS:
            return False
        self.seq = (self.seq + 1) % 256
        return True

    def _birth(self, board: Mapping[str, Any], image: ProcessImage | None) -> None:
        status = self.report.status if self.report is not None else ""
        self.report = Report(board, self.config.deadband)
        self.report.status = status
        self.seq = 0
        if self._publish("NBIRTH", self.report.birth(board, image, self.current_bdseq,
                                                     now_ms())):
            self.born, self.rebirth = True, False
            self.counts["births"] += 1
            self.last_data_s = time.monotonic()

    def _data(self, board: Mapping[str, Any], image: ProcessImage | None) -> None:
        assert self.client is not None and self.report is not None
        self.last_data_s = time.monotonic()
        metrics = self.report.changes(board, image, now_ms())
        if metrics and self._publish("NDATA", metrics):
            self.counts["data"] += 1


__all__ = ["COMMAND", "BdSeq", "EdgeNode"]
