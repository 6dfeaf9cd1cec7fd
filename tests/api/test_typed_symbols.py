"""Typed symbols over HTTP (core/present.py): reads show a real as a decimal number and an int
as a signed one, on the symbol routes, the forces, the status and the page's live frames;
writes and forces take typed values and refuse what the type cannot hold with one line naming
the symbol, its type and its range. A real ApiServer in front of a live scan loop."""

from __future__ import annotations

import http.client
import json
import time
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient, ApiError
from softplc.cli import main
from softplc.core.image import parse_address
from softplc.program import bundle
from tests.api.conftest import ServerThread
from tests.api.helpers import call
from tests.support import eventually

IO = """\
symbols:
  hold:   {address: "%MX0.0", type: bool}
  small:  {address: "%MW0", type: int}
  temp:   {address: "%MD0", type: real}
  count:  {address: "%MD1", type: dint}
  big:    {address: "%MD2", type: udint}
  level:  {address: "%ML0", type: lreal}
  out_t:  {address: "%QD0", type: real}
  out_n:  {address: "%QW0", type: int}
  pct:    {address: "%QW1", type: int, scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: "%"}}
"""
PROGRAM = """program: typed
io_image: io.yaml
places:
  idle: {tokens: 1}
  run: {}
transitions:
  begin: {from: [idle], to: [run],
          do: ["temp = 12.5", "small = -3", "count = -70000", "level = -1e300",
               "out_t = 0.1", "out_n = -42", "pct = 50.0"]}
"""
WRITTEN = {"temp": 12.5, "small": -3, "count": -70000, "level": -1e300, "out_t": 0.1,
           "out_n": -42, "hold": False, "big": 0}


@pytest.fixture
def client(api: ServerThread, tmp_path: Path) -> ApiClient:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "typed.yaml").write_text(PROGRAM, encoding="utf-8")
    client = ApiClient(api.url)
    client.download_bundle(bundle.pack(bundle.from_files(tmp_path / "typed.yaml")))
    eventually(lambda: client.status()["program"] == "typed", 60, "the download is applied")
    client.start()
    eventually(lambda: client.symbols().get("temp", {}).get("value") == 12.5, 30,
               "the program's typed writes are read typed")
    return client


def put(api: ServerThread, path: str, raw: bytes) -> tuple[int, dict[str, Any]]:
    answer = call(api.url, "PUT", f"/api/v1{path}", raw,
                  {"Content-Type": "application/json"}, owner=True)
    return answer.status, answer.body


def test_reads_show_typed_values(api: ServerThread, client: ApiClient) -> None:
    symbols = client.symbols()
    assert {name: symbols[name]["value"] for name in WRITTEN} == WRITTEN
    assert symbols["temp"] == {"name": "temp", "address": "%MD0", "type": "real",
                               "direction": "memory", "value": 12.5,
                               "raw": 0x41480000}  # 12.5's bits
    assert client.read_symbol("small") == -3 and client.read_symbol("count") == -70000
    assert client.read_symbol("out_t") == 0.1  # the stored single, as its shortest decimal


def test_writes_take_typed_values(api: ServerThread, client: ApiClient) -> None:
    for name, value in (("temp", -2.25), ("small", -32768), ("count", -(1 << 31)),
                        ("big", (1 << 32) - 1), ("level", 0.1), ("hold", True)):
        reply = client.write_symbol(name, value)
        assert reply["queued"] is True and reply["value"] == value
    written = {"temp": -2.25, "small": -32768, "count": -(1 << 31), "big": (1 << 32) - 1,
               "level": 0.1, "hold": True}

    def shown() -> dict[str, object]:
        symbols = client.symbols()
        return {n: symbols[n]["value"] for n in written}

    # Each write is applied by a scan of its own: wait for all of them, not for one (a loaded
    # run saw `level` applied and `hold`, written after it, not yet).
    eventually(lambda: shown() == written, 10, "the writes are applied", show=shown)
    assert client.write_symbol("small", 7.0)["value"] == 7  # JSON's whole float


@pytest.mark.parametrize(("name", "body", "error"), [
    ("small", b'{"value": 1.5}', "symbol small is an int: the value must be a whole number "
                                 "-32768..32767, not 1.5"),
    ("small", b'{"value": 40000}', "symbol small is an int: the value must be a whole number "
                                   "-32768..32767, not 40000"),
    ("big", b'{"value": -1}', "symbol big is a udint: the value must be a whole number "
                              "0..4294967295, not -1"),
    ("count", b'{"value": 2147483648}', "symbol count is a dint: the value must be a whole "
                                        "number -2147483648..2147483647, not 2147483648"),
    ("temp", b'{"value": NaN}', "symbol temp is a real: the value must be a finite number, "
                                "|x| <= 3.402823e+38, not NaN"),
    ("temp", b'{"value": 1e39}', "symbol temp is a real: the value must be a finite number, "
                                 "|x| <= 3.402823e+38, not 1e+39"),
    ("level", b'{"value": -Infinity}', "symbol level is an lreal: the value must be a finite "
                                       "number, not -Infinity"),
    ("temp", b'{"value": "12.5"}', "symbol temp is a real: the value must be a finite number, "
                                   '|x| <= 3.402823e+38, not "12.5"'),
])
def test_writes_and_forces_the_type_cannot_take_are_refused_in_one_line(
        api: ServerThread, client: ApiClient, name: str, body: bytes, error: str) -> None:
    for path in (f"/symbols/{name}", f"/forces/{name}"):
        status, answer = put(api, path, body)
        assert (status, answer["error"]) == (422, error), path
    assert client.forces() == {}


def test_forces_take_typed_values_and_show_them(api: ServerThread, client: ApiClient) -> None:
    assert client.force("out_t", 12.5)["message"] == "force: out_t = 12.5 (state RUNNING)"
    assert client.force("out_n", -7)["message"] == "force: out_n = -7 (state RUNNING)"
    assert client.force("level", 2.5e-300)["ok"]
    assert client.forces() == {"level": 2.5e-300, "out_n": -7, "out_t": 12.5}
    eventually(lambda: client.status()["forced"] == client.forces(), 10, "status typed")
    eventually(lambda: client.read_symbol("out_t") == 12.5 and client.read_symbol("out_n") == -7
               and client.read_symbol("level") == 2.5e-300, 10, "the forced values")
    client.unforce()
    eventually(lambda: client.read_symbol("out_t") == 0.1, 10, "the program's value again")


def test_the_cli_forces_text_as_the_symbols_type_takes_it(
        api: ServerThread, client: ApiClient, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["force", "out_t", "-2.5", "--api", api.url]) == 0
    assert "out_t = -2.5" in capsys.readouterr().out
    assert main(["force", "out_n", "-300", "--api", api.url]) == 0
    assert client.forces() == {"out_n": -300, "out_t": -2.5}
    assert main(["force", "out_n", "1.5", "--api", api.url]) == 1
    err = capsys.readouterr().err
    assert "symbol out_n is an int: the value must be a whole number -32768..32767, not 1.5" \
        in err
    assert main(["force", "out_t", "nan", "--api", api.url]) == 1
    assert "symbol out_t is a real" in capsys.readouterr().err
    assert main(["force", "out_t", "warm", "--api", api.url]) == 1
    assert "not true/false or a number" in capsys.readouterr().err
    eventually(lambda: main(["status", "--api", api.url]) == 0
               and "-2.5  FORCED" in capsys.readouterr().out, 10, "status shows -2.5")


def test_the_pages_live_frames_carry_typed_values(api: ServerThread, client: ApiClient) -> None:
    port = int(api.url.rsplit(":", 1)[1])
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    frame: dict[str, Any] = {}
    try:
        conn.request("GET", "/api/v1/live")
        response = conn.getresponse()
        assert response.status == 200
        end = time.monotonic() + 10
        while time.monotonic() < end and not frame.get("values"):
            line = response.readline()
            if line.startswith(b"data: "):
                frame = json.loads(line[6:])
    finally:
        conn.close()
    assert {n: frame["values"][n] for n in WRITTEN if n != "hold"} == \
        {n: v for n, v in WRITTEN.items() if n != "hold"}


def test_a_force_of_an_unknown_symbol_is_refused(client: ApiClient) -> None:
    with pytest.raises(ApiError) as refused:
        client.force("nope", 1.5)
    assert refused.value.status == 422 and "no symbol 'nope'" in refused.value.message


def test_a_scaled_symbol_is_read_written_and_forced_in_engineering_units(
        api: ServerThread, client: ApiClient) -> None:
    """The program wrote 50.0 %: the count 13824 is what the driver moves, 50.0 % is what
    every reader sees; writes and forces are given in % and scaled back as the program's
    writes are."""
    entry = client.symbols()["pct"]
    assert (entry["value"], entry["unit"], entry["scale"]["raw"]) == (50.0, "%", [0, 27648])
    assert raw_count(api) == 13824
    assert client.force("pct", 25.0)["message"] == "force: pct = 25.0 (state RUNNING)"
    eventually(lambda: client.read_symbol("pct") == 25.0 and raw_count(api) == 6912, 10,
               "forced at 25 %")
    assert client.forces() == {"pct": 25.0}
    client.unforce()
    status, body = put(api, "/symbols/pct", b'{"value": 200.0}')  # raw 55296: past an int
    assert status == 422 and "pct is scaled (0..100 % on an int)" in body["error"]


def raw_count(api: ServerThread) -> int:
    """What the image (the drivers' side) holds at pct's address, from the snapshot."""
    return int(api.server.snapshots.latest().image.get(parse_address("%QW1")))
