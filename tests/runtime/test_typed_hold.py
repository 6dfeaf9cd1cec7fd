"""The program's %QD and %QL outputs are kept like %QX and %QW while it does not drive them
(core/held.py): a stop drives them safe and a resume puts the program's values back; so do a
device fault and its recovery, and the wait for the first input image; retain keeps them
across a warm restart (runtime/retain/codec.py), and a file from before keeps %QX/%QW."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.core.present import shown
from softplc.core.problems import FaultCode
from softplc.runtime.retain import codec as retain_codec
from tests.core.helpers import Bench, compile_program

IO = """\
symbols:
  go:     {address: "%IX0.0", type: bool}
  lamp:   {address: "%QX0.0", type: bool}
  temp:   {address: "%QD0", type: real, safe: 0}
  count:  {address: "%QD1", type: dint, safe: 5}
  level:  {address: "%QL0", type: lreal, safe: 0}
"""
PROGRAM = """
places:
  idle: {tokens: 1}
  run: {outputs: [lamp]}
transitions:
  start: {from: [idle], to: [run], when: go,
          do: ["temp = 12.5", "count = -70000", "level = -0.125"]}
"""
PROGRAM_VALUES = {"lamp": True, "temp": 12.5, "count": -70000, "level": -0.125}
SAFE_VALUES = {"lamp": False, "temp": 0.0, "count": 5, "level": 0.0}


def values(bench: Bench) -> dict[str, object]:
    symbols = bench.net.io.symbols
    return {name: shown(symbols[name].type.value, bench.get(name)) for name in PROGRAM_VALUES}


@pytest.fixture
def bench(tmp_path: Path) -> Bench:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    bench = Bench(compile_program(tmp_path, PROGRAM))
    bench.set(go=1)
    bench.scan(10)
    assert values(bench) == PROGRAM_VALUES
    return bench


def test_a_resume_puts_back_the_double_and_long_word_outputs_of_the_program(
        bench: Bench) -> None:
    bench.scan(20, [ProgramCommand(Command.STOP)])
    assert values(bench) == SAFE_VALUES  # stopped: every output at its safe value
    bench.scan(30, [ProgramCommand(Command.RESUME)])
    assert bench.plc.state is PlcState.RUNNING and bench.marking() == {"run": 1}
    assert values(bench) == PROGRAM_VALUES  # nothing fired again: the kept values


def test_a_device_fault_and_its_recovery_keep_them_too(bench: Bench) -> None:
    bench.plc.fault(FaultCode.DEVICE, 20)
    assert bench.plc.state is PlcState.FAULTED and values(bench) == SAFE_VALUES
    assert bench.plc.recover(30) and values(bench) == PROGRAM_VALUES


def test_the_wait_for_the_first_input_image_keeps_them(bench: Bench) -> None:
    bench.plc.wait_for_io(20)
    assert values(bench) == SAFE_VALUES
    bench.plc.end_io_wait(30)
    assert values(bench) == PROGRAM_VALUES


def _retained(bench: Bench) -> dict[str, object]:
    cap = retain_codec.capture(bench.plc, 40, {})
    assert cap is not None
    payload: dict[str, object] = json.loads(json.dumps(retain_codec.encode(cap, 1, 0)))
    return payload


def _warm(bench: Bench, payload: dict[str, object]) -> Bench:
    again = Bench(bench.net, start=False)
    retain_codec.restore(again.plc, payload, resume=False)
    assert again.plc.state is PlcState.STOPPED and values(again) == SAFE_VALUES
    again.scan(50, [ProgramCommand(Command.RESUME)])
    return again


def test_retain_keeps_them_across_a_warm_restart(bench: Bench) -> None:
    bench.scan(20, [ProgramCommand(Command.STOP)])
    payload = _retained(bench)
    assert isinstance(payload["held"], list) and len(payload["held"]) == 4
    again = _warm(bench, payload)
    assert again.plc.state is PlcState.RUNNING and values(again) == PROGRAM_VALUES


def test_a_retain_file_from_before_keeps_bits_and_words_and_the_rest_safe(
        bench: Bench) -> None:
    bench.scan(20, [ProgramCommand(Command.STOP)])
    payload = _retained(bench)
    payload["held"] = payload["held"][:2]  # type: ignore[index]
    again = _warm(bench, payload)
    assert values(again) == {**SAFE_VALUES, "lamp": True}


def test_a_retained_force_of_a_real_comes_back_as_its_value(bench: Bench) -> None:
    raw = int(struct.unpack("<I", struct.pack("<f", -2.5))[0])
    (reply,) = bench.scan(20, [ProgramCommand(Command.FORCE, symbol="temp", value=raw)]).replies
    assert reply.message == "force: temp = -2.5 (state RUNNING)"
    bench.scan(30, [ProgramCommand(Command.STOP)])
    again = _warm(bench, _retained(bench))
    assert again.plc.forces.shown() == {"temp": -2.5} and values(again)["temp"] == -2.5
