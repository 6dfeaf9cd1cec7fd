"""A symbol locked by a download (`hmi_writable: false` added to its io image, the program
otherwise the same) is refused at every door from the moment the download is applied, as
one locked from the start is (tests/security/test_write_rule.py).

The doors keep what they built from the status board by the running program's hash (the
Modbus write predicate, the OPC UA address space, the Sparkplug door): a hash that left out
`hmi_writable:` stayed the same across that download, and on 7b93781 the Modbus slave kept
writing the symbol that HTTP refused. The program hash now covers `hmi_writable: false` and
`finite: false` where declared (program/io_image.py `hashed_text`), as it covers `init:`:
what the PLC accepts through its doors is its behaviour.
"""

from __future__ import annotations

import asyncio
import json
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api.client import ApiClient
from softplc.program.compiler import compile_file
from tests.api.helpers import Answer, call
from tests.hmi.helpers import connect, request
from tests.opcua.conftest import Plc
from tests.security.test_write_rule import (
    CHECKOUT,
    LOCKED,
    WORDS,
    _opcua_write,
    _symbol,
    transport_serving,
    with_symbol,
)
from tests.support import eventually


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[tuple[Plc, str, int, Path]]:
    """transport.yaml RUNNING with `speed` (%MW5) writable (test_write_rule.py's, unlocked);
    the io image's path, to lock `speed` in."""
    with transport_serving(tmp_path, OPEN) as (running, url, modbus):
        yield running, url, modbus, tmp_path / "io_images" / "transport.yaml"


OPEN = '  speed: {address: "%MW5", type: word}\n'  # LOCKED, but writable


def _locked(io: Path) -> None:
    text = io.read_text()
    assert OPEN in text
    io.write_text(text.replace(OPEN, LOCKED))


def _http_write(url: str, value: int) -> Answer:
    return call(url, "PUT", "/api/v1/symbols/speed", json.dumps({"value": value}),
                {"Content-Type": "application/json"}, owner=True)


def test_what_the_doors_enforce_is_in_the_program_hash(tmp_path: Path) -> None:
    """A symbol's `hmi_writable: false` or `finite: false` changes the hash; its description
    does not (a text, not a behaviour: a change of it alone keeps a warm start)."""
    for folder in ("programs", "io_images"):
        shutil.copytree(CHECKOUT / folder, tmp_path / folder)
    program = tmp_path / "programs" / "transport.yaml"
    io = tmp_path / "io_images" / "transport.yaml"
    text = io.read_text()

    def hashed(line: str) -> str:
        io.write_text(with_symbol(text, line))
        return compile_file(str(program)).program_hash

    assert hashed(LOCKED) != hashed(OPEN)
    finite = '  level_r: {address: "%MD7", type: real, finite: false}\n'
    assert hashed(finite) != hashed(finite.replace(", finite: false", ""))
    described = '  speed: {address: "%MW5", type: word, description: "belt speed"}\n'
    assert hashed(described) == hashed(OPEN)


def test_a_symbol_locked_by_an_online_change_is_refused_at_every_door(
        plc: tuple[Plc, str, int, Path]) -> None:
    opcua, url, modbus, io = plc
    with connect(modbus) as sock:  # FC 06 to %MW5: written while nothing locks it
        assert request(sock, bytes([6]) + (WORDS + 5).to_bytes(2, "big")
                       + (5).to_bytes(2, "big"))[0] == 6
    _locked(io)
    text = (CHECKOUT / "programs" / "transport.yaml").read_text()
    reply = ApiClient(url, token=opcua.token, timeout_s=60).download_text(
        text, online=True, name="transport.yaml")
    assert "online change" in str(reply), reply

    def http_refuses() -> bool:  # the value it holds: a write that is taken changes nothing
        return _http_write(url, 5).status == 403

    eventually(http_refuses, timeout_s=30, what="the HTTP door refusing speed")
    with connect(modbus) as sock:
        answer = request(sock, bytes([6]) + (WORDS + 5).to_bytes(2, "big")
                         + (77).to_bytes(2, "big"))
        assert answer == bytes([0x86, 0x02]), answer.hex()  # illegal data address
    http = _http_write(url, 77)
    assert http.status == 403 and b"hmi_writable: false" in http.raw, http.raw
    assert asyncio.run(_opcua_write(opcua)) in ("BadNotWritable", "BadUserAccessDenied")
    shown = _symbol(url)
    assert shown is not None and shown.get("raw") == 5, shown  # what Modbus wrote before
