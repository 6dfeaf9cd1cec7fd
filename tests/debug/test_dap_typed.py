"""The debug adapter shows what the net reads (issue 39 item 1, issue 40 item 5): on the
shipped tank program through a real `softplc run` and `softplc dap`, a breakpoint on
`start_fill` (set before the start, with the level and the temperature forced) stops the
editor's thread at the first scan; the Symbols scope and a hover show a `real` as a real
and a scaled symbol in engineering units at its scale's resolution with its unit
(core/present.py, as live `why` and the VCD), the stored bits in a child named `raw`."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Iterator

import pytest

from softplc.api.client import ApiClient
from tests.debug.test_dap import Dap, variables
from tests.support import ROOT, eventually, free_port, softplc_run, stop_process

PROGRAM = ROOT / "programs" / "tank.yaml"
START_FILL_LINE = 20  # `  start_fill:` in programs/tank.yaml


@pytest.fixture
def tank(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    state = tmp_path_factory.mktemp("state")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run([str(PROGRAM), "--plant", "tank", "--api", f"127.0.0.1:{port}",
                      "--modbus", f"127.0.0.1:{free_port()}", "--opcua", "off", "--state-dir",
                      str(state), "--quiet"],
                     lambda: ApiClient(url, timeout_s=2).status().get("program") == "tank"):
        yield url, str(state)


def test_symbols_and_hovers_are_typed_with_units_and_raw_children(
        tank: tuple[str, str]) -> None:
    url, state = tank
    assert PROGRAM.read_text().splitlines()[START_FILL_LINE - 1] == "  start_fill:"
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "softplc.cli", "dap", "--api", url,
                             "--state-dir", state, "--port", str(port)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        sock = eventually(lambda: socket.create_connection(
            ("127.0.0.1", port), timeout=5), 30, "softplc dap listening", step_s=0.1,
            errors=(OSError,))
        with sock:
            dap = Dap(sock)
            assert dap.request("initialize", adapterID="softplc", linesStartAt1=True)["success"]
            assert dap.request("attach", program=str(PROGRAM))["success"]
            placed = dap.request("setBreakpoints", source={"path": str(PROGRAM)},
                                 breakpoints=[{"line": START_FILL_LINE}])
            assert placed["body"]["breakpoints"][0]["verified"], placed
            assert dap.request("configurationDone")["success"]
            owner = ApiClient(url, state_dir=state)
            owner.force("level", 42.5)  # 0..27648 = 0..100 %: raw 11750, 42.499 %
            owner.force("temperature", 4.4)  # -500..1500 = -50..150 °C: raw 44, 4.4 °C
            owner.start()
            dap.event("stopped", 60)  # start_fill: 42.5 < 80 and 4.4 > 2.0

            frame, = dap.request("stackTrace", threadId=1)["body"]["stackFrames"]
            scopes = {s["name"]: s["variablesReference"]
                      for s in dap.request("scopes", frameId=frame["id"])["body"]["scopes"]}
            symbols = variables(dap, scopes["Symbols"])
            assert symbols["level"]["value"] == "42.499 % (forced)"
            assert symbols["temperature"]["value"] == "4.4 °C (forced)"
            assert symbols["fill_to"]["value"] == "80.0"  # a real, as the program reads it
            assert symbols["high_switch"]["value"] == "0"
            assert symbols["high_switch"]["variablesReference"] == 0  # a bit is its value
            raws = {name: variables(dap, symbols[name]["variablesReference"])["raw"]
                    for name in ("level", "temperature", "fill_to", "batches")}
            assert raws["level"]["value"] == "11750 (0x2DE6)"
            assert raws["level"]["type"] == "raw count of %IW0"
            assert raws["temperature"]["value"] == "44 (0x002C)"
            assert raws["fill_to"]["value"] == "1117782016 (0x42A00000)"  # 80.0's bits
            assert raws["fill_to"]["type"] == "stored bits of %MD2"
            assert raws["batches"]["value"] == "0 (0x00000000)"

            hover = dap.request("evaluate", expression="temperature")["body"]
            assert hover["result"] == "4.4 °C (forced)" and hover["variablesReference"] > 0
            assert variables(dap, hover["variablesReference"])["raw"]["value"] == "44 (0x002C)"
            assert dap.request("evaluate", expression="min_temp")["body"]["result"] == "2.0"
            why = variables(dap, scopes["Why start_fill"])  # the next round: idle is empty
            assert why["1. tokens"]["value"] == "idle: 0 of 1", why
            assert dap.request("disconnect")["success"]
    finally:
        stop_process(proc)
