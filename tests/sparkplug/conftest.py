"""Real parts for the Sparkplug tests: Debian's Mosquitto on a free loopback port (a generated
config: anonymous, user/password, TLS with openssl-made certificates), an independent codec
(Eclipse Tahu JS, npm `sparkplug-payload`, installed once into .venv/sparkplug-js; the tests
skip, saying why, without node/npm or mosquitto: .ci/run installs them), a host application
(paho-mqtt) that records what the broker delivers, and `softplc run` in its own session (so
that a test can SIGKILL the whole PLC)."""

from __future__ import annotations

import base64
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from tests.support import ROOT, free_port, npm_modules

NODE_DIR = Path(__file__).parent / "node"
CACHE = ROOT / ".venv" / "sparkplug-js"
WAIT_S = 45.0  # for any one message (a PLC start beside busy loops takes seconds)


@pytest.fixture(scope="session")
def node_modules() -> Path:
    return npm_modules(NODE_DIR, CACHE, "sparkplug-payload")


class Tahu:
    """Eclipse Tahu JS's codec, one node process per batch."""

    def __init__(self, node_modules: Path) -> None:
        self.env = {"NODE_PATH": str(node_modules), "PATH": os.environ.get("PATH", "/usr/bin")}

    def _run(self, requests: list[dict[str, Any]]) -> list[dict[str, Any]]:
        done = subprocess.run([shutil.which("node") or "node", str(NODE_DIR / "codec.js")],
                              input="".join(json.dumps(r) + "\n" for r in requests),
                              capture_output=True, text=True, timeout=30, check=False,
                              env=self.env)
        answers = [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
        assert len(answers) == len(requests), done.stderr[-2000:]
        for answer in answers:
            assert "error" not in answer, answer["error"]
        return answers

    def decode(self, payloads: list[bytes]) -> list[dict[str, Any]]:
        """[{"payload": Tahu's object, "raw": the protobuf message's fields}, ...]"""
        return self._run([{"decode": base64.b64encode(p).decode()} for p in payloads])

    def encode(self, payload: dict[str, Any]) -> bytes:
        return base64.b64decode(self._run([{"encode": payload}])[0]["b64"])


@pytest.fixture(scope="session")
def tahu(node_modules: Path) -> Tahu:
    return Tahu(node_modules)


@dataclass
class Broker:
    port: int
    proc: subprocess.Popen[bytes]
    log: Path
    dir: Path

    def log_text(self) -> str:
        return self.log.read_text(errors="replace")


def _openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def make_certs(where: Path) -> Path:
    """A CA and a broker certificate for 127.0.0.1 signed by it; the CA file's path."""
    where.mkdir(parents=True, exist_ok=True)
    _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", "ca.key", "-out", "ca.crt", "-days", "2", "-subj", "/CN=test CA",
             cwd=where)
    _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
             "-keyout", "broker.key", "-out", "broker.csr", "-subj", "/CN=127.0.0.1", cwd=where)
    (where / "ext.cnf").write_text("subjectAltName=IP:127.0.0.1\n")
    _openssl("x509", "-req", "-in", "broker.csr", "-CA", "ca.crt", "-CAkey", "ca.key",
             "-CAcreateserial", "-out", "broker.crt", "-days", "2", "-extfile", "ext.cnf",
             cwd=where)
    return where / "ca.crt"


@pytest.fixture
def mosquitto(tmp_path: Path) -> Iterator[Callable[..., Broker]]:
    """Start Mosquitto: `mosquitto(users={"u": "pw"}, tls=True)`; stopped at the end."""
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not Path(binary).exists():
        pytest.skip("mosquitto not installed (apt-get install mosquitto; .ci/run does)")
    started: list[Broker] = []

    def start(users: dict[str, str] | None = None, tls: bool = False) -> Broker:
        where = tmp_path / f"broker{len(started)}"
        where.mkdir()
        port = free_port()
        lines = [f"listener {port} 127.0.0.1", "persistence false", "log_dest stderr",
                 "log_type all", "user root"]
        if users:
            passwd = where / "passwd"
            passwd.write_text("")
            for user, password in users.items():
                subprocess.run(["mosquitto_passwd", "-b", str(passwd), user, password],
                               check=True, capture_output=True, timeout=30)
            lines += ["allow_anonymous false", f"password_file {passwd}"]
        else:
            lines.append("allow_anonymous true")
        if tls:
            make_certs(where)
            lines += [f"cafile {where / 'ca.crt'}", f"certfile {where / 'broker.crt'}",
                      f"keyfile {where / 'broker.key'}"]
        (where / "m.conf").write_text("\n".join(lines) + "\n")
        log = where / "mosquitto.log"
        with log.open("wb") as err:
            proc = subprocess.Popen([binary, "-c", str(where / "m.conf")], stderr=err,
                                    stdout=subprocess.DEVNULL)
        broker = Broker(port, proc, log, where)
        started.append(broker)
        deadline = time.monotonic() + 10
        while f"port {port}" not in broker.log_text() or "running" not in broker.log_text():
            assert proc.poll() is None, broker.log_text()
            assert time.monotonic() < deadline, broker.log_text()
            time.sleep(0.02)
        return broker

    yield start
    for broker in started:
        broker.proc.terminate()
        try:
            broker.proc.wait(5)
        except subprocess.TimeoutExpired:
            broker.proc.kill()
            broker.proc.wait(5)


@dataclass
class Message:
    topic: str
    payload: bytes
    qos: int
    retain: bool


@dataclass
class Host:
    """A host application: records every message under spBv1.0/# and publishes commands."""

    client: mqtt.Client
    messages: list[Message] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def since(self, start: int, kind: str) -> list[tuple[int, Message]]:
        with self.lock:
            return [(i, m) for i, m in enumerate(self.messages)
                    if i >= start and m.topic.split("/")[2:3] == [kind]]

    def wait(self, kind: str, start: int = 0, timeout_s: float = WAIT_S) -> tuple[int, Message]:
        """The first message of `kind` (NBIRTH, NDATA, ...) at or after index `start`."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            found = self.since(start, kind)
            if found:
                return found[0]
            time.sleep(0.01)
        raise AssertionError(f"no {kind} within {timeout_s} s; got "
                             f"{[m.topic for m in self.messages][-10:]}")

    def count(self) -> int:
        with self.lock:
            return len(self.messages)

    def send(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False) -> None:
        self.client.publish(topic, payload, qos=qos, retain=retain).wait_for_publish(5)


@pytest.fixture
def host() -> Iterator[Callable[..., Host]]:
    made: list[Host] = []

    def connect(port: int, user: str | None = None, password: str | None = None,
                ca: str | None = None) -> Host:
        client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"test-host-{len(made)}")
        if user is not None:
            client.username_pw_set(user, password)
        if ca is not None:
            client.tls_set(ca_certs=ca)
        h = Host(client)
        subscribed = threading.Event()

        def on_message(c: Any, u: Any, msg: mqtt.MQTTMessage) -> None:
            with h.lock:
                h.messages.append(Message(msg.topic, msg.payload, msg.qos, bool(msg.retain)))

        client.on_message = on_message
        client.on_connect = lambda c, u, f, r, p: c.subscribe("spBv1.0/#", qos=1)
        client.on_subscribe = lambda c, u, m, r, p: subscribed.set()
        client.connect("127.0.0.1", port, keepalive=30)
        client.loop_start()
        assert subscribed.wait(10), "the host could not subscribe"
        made.append(h)
        return h

    yield connect
    for h in made:
        h.client.loop_stop()
        h.client.disconnect()


def start_plc(state_dir: Path, sparkplug: str, *extra: str, program: str = "programs/tank.yaml",
              env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """`softplc run` in a session of its own (os.killpg kills the whole PLC)."""
    state_dir.mkdir(parents=True, exist_ok=True)
    args = [sys.executable, "-m", "softplc.cli", "run", program, "--start", "--modbus", "off",
            "--opcua", "off", "--state-dir", str(state_dir), "--quiet",
            "--sparkplug", sparkplug, *extra]
    if "--api" not in extra:
        args += ["--api", "off"]
    log = (state_dir / "run.log").open("a")
    proc = subprocess.Popen(args, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, env={**os.environ, **(env or {})})
    log.close()
    return proc


def stop_plc(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


def kill_plc(proc: subprocess.Popen[str]) -> None:
    """SIGKILL to the PLC's whole process group: nobody sends an NDEATH but the broker."""
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(10)


def metrics_of(decoded: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """A decoded birth's metrics by name."""
    return {m["name"]: m for m in decoded["payload"]["metrics"]}
