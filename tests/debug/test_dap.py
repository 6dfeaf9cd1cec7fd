"""`softplc dap` over the wire (issue 32 item 5): a scripted DAP client (a plain socket and
the Content-Length framing written here, not the adapter's) against a real `softplc run` of
the transport program: a breakpoint on the line of `handed_over` stops the editor's thread,
the frame is that line, the variables are the marking, the symbols and why; `next` is one
scan; `disconnect` leaves the PLC running with no breakpoints. And `initialize` over stdio."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest

from softplc.api.client import ApiClient
from tests.debug.live import status, transport_plc
from tests.support import ROOT, eventually, free_port, stop_process

PROGRAM = ROOT / "programs" / "transport.yaml"
HANDED_OVER_LINE = 25  # `  handed_over:` in programs/transport.yaml


def _frame(message: dict[str, Any]) -> bytes:
    body = json.dumps(message).encode()
    return b"Content-Length: %d\r\n\r\n" % len(body) + body


class Dap:
    """An editor's side of a DAP connection, as bare as the protocol allows."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock, self.file = sock, sock.makefile("rb")
        self.seq, self.events = 0, list[dict[str, Any]]()

    def request(self, command: str, timeout_s: float = 30.0, **arguments: Any) -> dict[str, Any]:
        self.seq += 1
        seq = self.seq
        self.sock.sendall(_frame({"seq": seq, "type": "request", "command": command,
                                  "arguments": arguments}))
        deadline = time.monotonic() + timeout_s
        while True:
            message = self.read(deadline)
            if message["type"] == "response" and message["request_seq"] == seq:
                assert message["command"] == command
                return message
            self.events.append(message)

    def event(self, name: str, timeout_s: float,
              where: Callable[[dict[str, Any]], bool] = lambda body: True) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while True:
            for message in self.events:
                if message["event"] == name and where(message.get("body") or {}):
                    self.events.remove(message)
                    return dict(message.get("body") or {})
            self.events.append(self.read(deadline))

    def read(self, deadline: float) -> dict[str, Any]:
        self.sock.settimeout(max(0.01, deadline - time.monotonic()))
        length = None
        while (line := self.file.readline()) not in (b"\r\n", b""):
            name, _, value = line.decode("ascii").partition(":")
            if name.strip().lower() == "content-length":
                length = int(value)
        assert length is not None, "the adapter closed the connection"
        message: dict[str, Any] = json.loads(self.file.read(length))
        return message


@pytest.fixture(scope="module")
def plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    with transport_plc(tmp_path_factory) as running_plc:
        yield running_plc


@pytest.fixture
def dap(plc: tuple[str, str]) -> Iterator[Dap]:
    """`softplc dap --port P` as the owner of the PLC (its state directory's key)."""
    url, state = plc
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "softplc.cli", "dap", "--api", url,
                             "--state-dir", state, "--port", str(port)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        sock = eventually(lambda: socket.create_connection(("127.0.0.1", port), timeout=5),
                          30, "softplc dap listening", step_s=0.1, errors=(OSError,))
        with sock:
            yield Dap(sock)
    finally:
        stop_process(proc)


def variables(dap: Dap, ref: int) -> dict[str, dict[str, Any]]:
    reply = dap.request("variables", variablesReference=ref)
    assert reply["success"], reply
    return {v["name"]: v for v in reply["body"]["variables"]}


def test_breakpoint_on_a_line_next_continue_disconnect(plc: tuple[str, str], dap: Dap) -> None:
    url, _ = plc
    caps = dap.request("initialize", adapterID="softplc", linesStartAt1=True,
                       columnsStartAt1=True)
    assert caps["success"] and caps["body"]["supportsConfigurationDoneRequest"]
    attach = dap.request("attach", program=str(PROGRAM))
    assert attach["success"], attach
    dap.event("initialized", 10)
    placed = dap.request("setBreakpoints", source={"path": str(PROGRAM)},
                         breakpoints=[{"line": HANDED_OVER_LINE + 2}, {"line": 3}])
    first, outside = placed["body"]["breakpoints"]
    assert first["verified"] and first["line"] == HANDED_OVER_LINE  # moved to the key line
    assert not outside["verified"] and "no transition at line 3" in outside["message"]
    plc_points = eventually(lambda: status(url)["breakpoints"], 10, "the PLC's breakpoint")
    assert [(p["on"], p["target"]) for p in plc_points] == [("fire", "handed_over")]
    assert dap.request("configurationDone")["success"]

    stopped = dap.event("stopped", 90)
    assert stopped["reason"] == "breakpoint" and stopped["threadId"] == 1
    assert stopped["hitBreakpointIds"] == [first["id"]]
    paused = status(url)["paused"]
    count = paused["scan_count"]
    assert f"scan count {count}" in stopped["description"]
    threads = dap.request("threads")["body"]["threads"]
    assert threads == [{"id": 1, "name": "scan"}]
    frame, = dap.request("stackTrace", threadId=1)["body"]["stackFrames"]
    assert frame["line"] == HANDED_OVER_LINE and frame["source"]["path"] == str(PROGRAM)
    assert frame["name"].startswith("handed_over fires")
    scopes = {s["name"]: s["variablesReference"]
              for s in dap.request("scopes", frameId=frame["id"])["body"]["scopes"]}
    assert set(scopes) == {"Marking", "Symbols", "Why handed_over"}

    marking = variables(dap, scopes["Marking"])
    assert {"handing_over", "delivered", "c1.idle", "c2.idle", "c1.full"} <= set(marking)
    now = status(url)  # paused: the marking stands
    assert {n: int(v["value"]) for n, v in marking.items() if v["value"] != "0"} \
        == {n: c for n, c in now["marking"].items() if c}
    assert marking["delivered"]["variablesReference"] > 0  # a coloured place's records
    symbols = variables(dap, scopes["Symbols"])
    plc_symbols = ApiClient(url).symbols()
    assert set(symbols) == set(plc_symbols)
    assert symbols["m1"]["type"].startswith("bool out")
    assert symbols["hold"]["value"] == str(int(plc_symbols["hold"]["value"]))  # as why: 0/1
    why = variables(dap, scopes["Why handed_over"])
    assert why["verdict"]["value"] in ("fires", "blocked", "waiting", "lost")
    assert dap.request("evaluate", expression="hold")["body"]["result"] in ("0", "1")
    assert not dap.request("pause", threadId=1)["success"]  # the PLC has no pause-now

    assert dap.request("next", threadId=1)["success"]
    stepped = dap.event("stopped", 30)
    assert stepped["reason"] == "step" and f"scan count {count + 1}" in stepped["description"]
    assert status(url)["paused"]["scan_count"] == count + 1
    frame, = dap.request("stackTrace", threadId=1)["body"]["stackFrames"]
    assert frame["name"] == f"transport after scan {count}" and frame["line"] == 1

    assert dap.request("continue", threadId=1)["success"]
    eventually(lambda: status(url)["scan_count"] > count + 5, 20, "running on")
    assert dap.request("disconnect")["success"]
    eventually(lambda: not (s := status(url)).get("breakpoints") and not s.get("paused"), 10,
               "no breakpoints, not paused", step_s=0.1)
    ran = status(url)["scan_count"]
    eventually(lambda: status(url)["scan_count"] > ran + 5, 20, "running after the session")
    assert status(url)["state"] == "RUNNING"


def test_initialize_over_stdio() -> None:
    """As an editor launches an adapter: DAP on stdin and stdout; the end of stdin ends it."""
    message = {"seq": 1, "type": "request", "command": "initialize",
               "arguments": {"adapterID": "softplc"}}
    done = subprocess.run([sys.executable, "-m", "softplc.cli", "dap", "--api",
                           f"http://127.0.0.1:{free_port()}"], cwd=ROOT, input=_frame(message),
                          capture_output=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    header, _, body = done.stdout.partition(b"\r\n\r\n")
    assert header == b"Content-Length: %d" % len(body)
    reply = json.loads(body)
    assert (reply["type"], reply["command"], reply["success"]) == ("response", "initialize", True)
    assert reply["body"]["supportsConfigurationDoneRequest"] is True
