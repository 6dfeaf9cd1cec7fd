"""Modbus write restriction end to end: CommConfig.modbus_writes -> the slave that the
communication process builds (runtime/serve/comm.py) -> a real socket, in front of a live scan.

"open" (default, OpenPLC): outputs and memory writable but the locations of symbols declared
`hmi_writable: false` (refused at every door: security/writes.py); "symbols": only the running
program's out/memory symbols not declared `hmi_writable: false`, following downloads;
"none": read-only. A refused write is exception 02 and the image does not change.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.core.image import parse_address
from softplc.core.lifecycle import Command
from softplc.runtime.serve.comm import CommConfig, ModbusWrites, modbus_slave
from tests.fuzz.live import LivePlc
from tests.hmi.helpers import SlaveThread, connect, request, run_in_thread
from tests.support import eventually

ROOT = Path(__file__).resolve().parents[2]
EXTRA_SYMBOLS = """
  setpoint: {address: "%MW4", type: word, description: "HMI setting"}
  speed: {address: "%MW5", type: word, hmi_writable: false, description: "read-only for HMIs"}
"""
WORDS = 1024  # default image: holding registers 0..1023 are %QW, 1024.. are %MW
BITS = 800  # coils 0..799 are %QX, 800.. are %MX
REFUSED = 0x02


def _tree(tmp: Path) -> Path:
    """A program root with transport.yaml and drilling.yaml; transport's io image declares
    two more memory words, one of them not HMI-writable."""
    shutil.copytree(ROOT / "programs", tmp / "programs")
    shutil.copytree(ROOT / "io_images", tmp / "io_images")
    io = tmp / "io_images" / "transport.yaml"
    text = io.read_text()
    io.write_text(text.replace("\nevents:", EXTRA_SYMBOLS + "\nevents:", 1))
    return tmp


@pytest.fixture
def plc(tmp_path: Path) -> Iterator[LivePlc]:
    root = _tree(tmp_path)
    with LivePlc(root, root / "programs" / "transport.yaml") as live:
        eventually(lambda: live.document().get("state") == "RUNNING")
        yield live


def _slave(plc: LivePlc, mode: ModbusWrites) -> SlaveThread:
    # The slave audits its writes into the state directory: the test's, not the checkout's.
    config = CommConfig(modbus=("127.0.0.1", 0), modbus_writes=mode,
                        state_dir=f"{plc.loop.config.root}/state")
    return run_in_thread(modbus_slave(config, plc.reader, plc.channel.send_hmi_write,
                                      plc.board.read))


def write_coil(sock, coil: int, on: bool = True) -> bytes:  # type: ignore[no-untyped-def]
    return request(sock, bytes([5]) + coil.to_bytes(2, "big") + (b"\xff\x00" if on else b"\0\0"))


def write_register(sock, register: int, value: int) -> bytes:  # type: ignore[no-untyped-def]
    return request(sock, bytes([6]) + register.to_bytes(2, "big") + value.to_bytes(2, "big"))


def write_registers(sock, register: int, values: list[int]) -> bytes:  # type: ignore[no-untyped-def]
    body = b"".join(v.to_bytes(2, "big") for v in values)
    return request(sock, bytes([16]) + register.to_bytes(2, "big")
                   + len(values).to_bytes(2, "big") + bytes([len(body)]) + body)


def image_value(plc: LivePlc, address: str) -> int:
    plc.settled()
    return int(plc.reader.latest().image.get(parse_address(address)))


def refused(reply: bytes, function_code: int) -> bool:
    return reply == bytes([function_code | 0x80, REFUSED])


def accepted(reply: bytes, function_code: int) -> bool:
    return reply[0] == function_code


def test_open_is_the_default_and_writes_outputs_and_memory(plc: LivePlc) -> None:
    assert CommConfig().modbus_writes == "open"
    with _slave(plc, "open") as slave, connect(slave.port) as sock:
        assert accepted(write_register(sock, WORDS + 4, 42), 6)  # setpoint
        assert accepted(write_register(sock, WORDS + 300, 9), 6)  # no symbol there
        assert accepted(write_coil(sock, BITS + 1), 5)  # %MX0.1, no symbol
        # speed is declared hmi_writable: false: no door writes it, Modbus "open" neither
        eventually(lambda: refused(write_register(sock, WORDS + 5, 77), 6))
        assert refused(write_registers(sock, WORDS + 4, [1, 2]), 16)  # all or nothing
        assert image_value(plc, "%MW4") == 42
        assert image_value(plc, "%MW5") == 0
        assert image_value(plc, "%MW300") == 9
        assert image_value(plc, "%MX0.1") == 1


def test_none_refuses_every_write_with_02_and_still_reads(plc: LivePlc) -> None:
    with _slave(plc, "none") as slave, connect(slave.port) as sock:
        assert refused(write_coil(sock, BITS), 5)  # hold
        assert refused(write_register(sock, WORDS + 4, 3), 6)  # setpoint
        assert refused(write_registers(sock, WORDS + 4, [1, 2]), 16)
        fc23 = bytes.fromhex("17" "0400" "0001" "0404" "0001" "02" "0007")
        assert refused(request(sock, fc23), 23)
        assert request(sock, bytes.fromhex("0304040001"))[0] == 3  # reads are served
        assert image_value(plc, "%MX0.0") == 0
        assert image_value(plc, "%MW4") == 0


def test_symbols_allows_exactly_the_hmi_writable_symbols(plc: LivePlc) -> None:
    with _slave(plc, "symbols") as slave, connect(slave.port) as sock:
        assert accepted(write_coil(sock, BITS), 5)  # hold, %MX0.0
        assert accepted(write_register(sock, WORDS + 4, 42), 6)  # setpoint, %MW4
        assert refused(write_register(sock, WORDS + 5, 43), 6)  # speed: hmi_writable false
        assert refused(write_register(sock, WORDS + 300, 9), 6)  # no symbol
        assert refused(write_coil(sock, BITS + 1), 5)  # %MX0.1, no symbol
        assert refused(write_coil(sock, 5), 5)  # %QX0.5, no symbol
        # all or nothing: setpoint is writable, speed next to it is not
        assert refused(write_registers(sock, WORDS + 4, [1, 2]), 16)
        assert image_value(plc, "%MX0.0") == 1
        assert image_value(plc, "%MW4") == 42
        assert image_value(plc, "%MW5") == 0
        assert image_value(plc, "%MW300") == 0
        assert image_value(plc, "%MX0.1") == 0


def test_symbols_follows_a_download(plc: LivePlc) -> None:
    with _slave(plc, "symbols") as slave, connect(slave.port) as sock:
        assert refused(write_register(sock, WORDS + 0, 5), 6)  # %MW0: not a transport symbol
        assert refused(write_coil(sock, 2), 5)  # %QX0.2: not a transport symbol
        assert plc.command(Command.STOP).ok
        drilling = (plc.loop.config.root or "") + "/programs/drilling.yaml"
        reply = plc.command(Command.DOWNLOAD, Path(drilling).read_text(), "drilling.yaml")
        assert reply.ok, reply.message
        # drill_down is %QX0.2 in drilling's io image; %MW0 is a symbol in neither
        eventually(lambda: accepted(write_coil(sock, 2), 5))
        assert refused(write_register(sock, WORDS + 0, 5), 6)
        assert image_value(plc, "%MW0") == 0


def test_unknown_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="modbus_writes must be one of open, symbols, none"):
        CommConfig(modbus_writes="all")  # type: ignore[arg-type]
