"""`GET /api/v1/history` against a real `softplc run` (docs/debug.md, the recent past): values
typed as their symbols read, the window bounded by SOFTPLC_HISTORY_SCANS, the scans the HTTP
process did not see (it was stopped) reported as a gap, bad parameters refused."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient
from softplc.runtime.shared.procs import children
from tests.api.helpers import call
from tests.support import eventually, free_port, softplc_run

KEPT = 150  # SOFTPLC_HISTORY_SCANS of the process under test
IO = """\
symbols:
  run_i:  {address: "%IX0.0", type: bool}
  small:  {address: "%MW0", type: int}
  temp:   {address: "%MD0", type: real}
  lamp:   {address: "%QX0.0", type: bool}
"""
PROGRAM = """program: typed
io_image: io.yaml
places:
  idle: {tokens: 1}
  lit: {}
transitions:
  light: {from: [idle], to: [lit], delay: 300ms, do: ["temp = 12.5", "small = -3", "set lamp"]}
"""


@pytest.fixture(scope="module")
def plc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ApiClient, int]]:
    folder = tmp_path_factory.mktemp("history")
    (folder / "io.yaml").write_text(IO, encoding="utf-8")
    (folder / "typed.yaml").write_text(PROGRAM, encoding="utf-8")
    port = free_port()
    client = ApiClient(f"http://127.0.0.1:{port}", timeout_s=10)
    os.environ["SOFTPLC_HISTORY_SCANS"] = str(KEPT)  # inherited by softplc run's processes
    try:
        with softplc_run([str(folder / "typed.yaml"), "--start", "--modbus", "off",
                          "--opcua", "off", "--api",
                          f"127.0.0.1:{port}", "--state-dir", str(folder / "state"), "--quiet",
                          "--period", "10ms"],
                         lambda: client.status()["state"] == "RUNNING") as proc:
            yield client, proc.pid
    finally:
        del os.environ["SOFTPLC_HISTORY_SCANS"]


def history(client: ApiClient, query: str = "") -> Any:
    answer = call(client.url, "GET", "/api/v1/history" + query)
    assert answer.status == 200, answer.body
    return answer.body


def test_values_marking_and_fired_are_typed(plc: tuple[ApiClient, int]) -> None:
    client, _ = plc
    window = eventually(lambda: (w := history(client, "?symbols=small,temp,lamp&places=lit"))
                        ["values"]["temp"][-1:] == [12.5] and w, 30, "the program's writes")
    assert window["types"] == {"small": "int", "temp": "real", "lamp": "bool"}
    assert window["values"]["small"][-1] == -3 and window["values"]["lamp"][-1] is True
    assert window["values"]["temp"][0] in (0.0, 12.5)
    assert set(window["values"]) == {"small", "temp", "lamp"} and window["program"] == "typed"
    assert len(window["t_ms"]) == len(window["scans"]) == len(window["state"])
    assert window["state"][-1] == "RUNNING"
    board = eventually(lambda: (b := history(client, "?symbols=&places=lit,idle")["board"])
                       ["marking"]["lit"][-1:] == [1] and b, 10, "lit marked on the board")
    assert board["marking"]["idle"][-1] == 0 and len(board["fired"]) == len(board["scans"])
    everything = history(client)  # no names: every symbol and place
    assert set(everything["values"]) == {"run_i", "small", "temp", "lamp"}
    assert set(everything["board"]["marking"]) == {"idle", "lit"}


def test_the_window_is_bounded(plc: tuple[ApiClient, int]) -> None:
    client, _ = plc
    eventually(lambda: client.status()["scan_count"] > 2 * KEPT, 60, "enough scans")
    window = history(client, "?symbols=lamp&places=")
    assert window["capacity"]["scans"] == KEPT and len(window["scans"]) <= KEPT
    assert window["oldest_scan"] == window["scans"][0] > KEPT // 2
    assert window["capacity"]["bytes"] <= window["capacity"]["max_bytes"] == 16 << 20
    last = window["scans"][-1]
    later = eventually(lambda: (w := history(client, f"?since={last}"))["scans"] and w, 10,
                       "scans after the last one seen")
    assert later["scans"][0] > last


def http_process(supervisor: int, port: int) -> int:
    """The child of `supervisor` listening on `port` (/proc, Linux)."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[3] == "0A" and int(fields[1].rsplit(":", 1)[1], 16) == port:
            inodes.add(f"socket:[{fields[9]}]")
    for pid in children(supervisor):
        with contextlib.suppress(OSError):
            if any(os.readlink(fd) in inodes for fd in Path(f"/proc/{pid}/fd").iterdir()):
                return pid
    raise AssertionError(f"no child of {supervisor} listens on {port}")


def test_scans_not_seen_are_a_gap(plc: tuple[ApiClient, int]) -> None:
    client, supervisor = plc
    http = http_process(supervisor, int(client.url.rsplit(":", 1)[1]))
    before = history(client, "?symbols=&places=")["scans"][-1]
    os.kill(http, signal.SIGSTOP)  # the sampler is stopped with it; the scan goes on
    try:
        time.sleep(0.5)
    finally:
        os.kill(http, signal.SIGCONT)
    # The scan process scanned meanwhile (each later scan number proves it): the first scan
    # sampled after the stop is past a gap that starts after `before`.
    window = eventually(lambda: (w := history(client, f"?since={before - 1}&symbols=&places="))
                        ["gaps"] and w, 10, "a gap after the stop")
    first, last = next((a, b) for a, b in window["gaps"] if a > before)
    assert last >= first and last + 1 in window["scans"] and first - 1 in window["scans"]
    sampled, missing = set(window["scans"]), {s for a, b in window["gaps"]
                                             for s in range(a, b + 1)}
    assert not sampled & missing
    assert sampled | missing == set(range(window["scans"][0], window["scans"][-1] + 1))


def test_bad_parameters_are_refused(plc: tuple[ApiClient, int]) -> None:
    client, _ = plc
    for query, needle in (("?since=soon", "since must be a scan number"),
                          ("?symbols=nothing", "no symbol 'nothing'"),
                          ("?places=nowhere", "no place 'nowhere'"),
                          ("?symbols=" + ",".join(["lamp"] * 65), "at most 64 symbols")):
        answer = call(client.url, "GET", "/api/v1/history" + query)
        assert answer.status == 400 and needle in answer.body["error"], answer.body
