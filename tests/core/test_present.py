"""What an operator or a client sees of a typed symbol, and what they may give it
(core/present.py), and the forcing of typed symbols in the pure scan (core/forcing.py keeps
raw bits; a force is reported typed). No socket, no sleep."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from softplc.core.datatypes import SymType
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import ProgramCommand
from softplc.core.present import (
    ValueRefused,
    accepted,
    decimals,
    plotted,
    raw_text,
    shown,
    shown_number,
)
from softplc.core.scaling import Scaling
from tests.core.helpers import Bench, compile_program

IO = """\
symbols:
  go:     {address: "%IX0.0", type: bool}
  temp:   {address: "%ID0", type: real}
  small:  {address: "%QW0", type: int}
  count:  {address: "%QD0", type: dint}
  big:    {address: "%QD1", type: udint}
  level:  {address: "%QL0", type: lreal}
  setp:   {address: "%MD0", type: real}
"""
PROGRAM = """
places:
  idle: {tokens: 1}
  run: {}
transitions:
  start: {from: [idle], to: [run], when: go, do: ["small = -3", "count = -70000", "level = 2.5"]}
"""


def f32(value: float) -> int:
    return int(struct.unpack("<I", struct.pack("<f", value))[0])


def test_raw_bits_show_as_their_type_reads_them() -> None:
    assert shown("real", f32(12.5)) == 12.5
    assert shown("real", f32(0.1)) == 0.1  # the shortest decimal that is the stored single
    assert shown("int", 0xFFFD) == -3
    assert shown("dint", 0xFFFEEE90) == -70000
    assert shown("udint", 0xFFFFFFFF) == 4294967295
    assert shown("word", 65535) == 65535
    assert shown("lreal", int(struct.unpack("<Q", struct.pack("<d", -1e300))[0])) == -1e300
    assert shown("bool", 1) is True and shown_number("bool", 1) == 1
    # JSON carries no NaN: a real that holds one says so as text, never as a number
    assert shown("real", 0x7FC00000) == "NaN"
    assert shown("real", 0xFF800000) == "-Infinity"
    assert shown("lreal", 0x7FF0000000000000) == "Infinity"
    assert shown(None, 42) == 42 and shown("float", 42) == 42  # unknown: the bits


LEVEL = Scaling((0, 27648), (0.0, 100.0), "%", clamp=True)
TEMP = Scaling((-500, 1500), (-50.0, 150.0), "°C")


def test_text_is_a_value_with_its_unit_at_the_scales_resolution() -> None:
    """What `why` and other texts show (issue 39): a real as a real, never its bits; a scaled
    symbol in engineering units with as many decimals as one raw count needs."""
    assert raw_text("real", f32(80.0)) == "80.0" and raw_text("real", f32(0.1)) == "0.1"
    assert raw_text("real", 0x7FC00000) == "NaN"
    assert decimals(LEVEL) == 3 and decimals(TEMP) == 1  # 0.0036 and 0.1 per count
    assert decimals(Scaling((0, 10), (0.0, 100.0))) == 0
    assert decimals(Scaling((0.0, 1.0), (0.0, 100.0), whole=False)) is None  # a real: no count
    assert raw_text("int", 23500, LEVEL) == "84.997 %"
    assert raw_text("int", 44, TEMP) == "4.4 °C"
    assert raw_text("int", 0xFFFF, TEMP) == "-0.1 °C"  # raw -1, signed
    assert raw_text("int", 0, Scaling((-10, 10), (-1.0, 1.0))) == "0.0"  # never "-0.0"
    assert raw_text("int", 0xFFFD) == "-3" and raw_text("bool", 1) == "1"
    assert plotted("int", 23500, LEVEL) == 84.997 and plotted("int", 44, TEMP) == 4.4
    assert plotted("real", f32(80.0)) == 80.0 and plotted("int", 0xFFFD) == -3


def test_typed_values_become_the_bits_a_program_write_stores() -> None:
    assert accepted("real", 12.5, "t") == f32(12.5)
    assert accepted("real", 3, "t") == f32(3.0)
    assert accepted("int", -3, "s") == 0xFFFD
    assert accepted("int", -3.0, "s") == 0xFFFD  # JSON's whole float is a whole number
    assert accepted("dint", -(1 << 31), "c") == 1 << 31
    assert accepted("udint", (1 << 32) - 1, "b") == (1 << 32) - 1
    assert accepted("bool", True, "g") == 1 and accepted("bool", 0, "g") == 0
    assert accepted("lreal", 0.1, "l") == int(struct.unpack("<Q", struct.pack("<d", 0.1))[0])


@pytest.mark.parametrize(("type_name", "value", "text"), [
    ("int", 1.5, "symbol s is an int: the value must be a whole number -32768..32767, not 1.5"),
    ("int", 40000, "symbol s is an int: the value must be a whole number -32768..32767, "
                   "not 40000"),
    ("word", -1, "symbol s is a word: the value must be a whole number 0..65535, not -1"),
    ("dint", 1 << 31, "symbol s is a dint: the value must be a whole number "
                      "-2147483648..2147483647, not 2147483648"),
    ("udint", -1, "symbol s is a udint: the value must be a whole number 0..4294967295, not -1"),
    ("real", math.nan, "symbol s is a real: the value must be a finite number, "
                       "|x| <= 3.402823e+38, not NaN"),
    ("real", 1e39, "symbol s is a real: the value must be a finite number, |x| <= 3.402823e+38, "
                   "not 1e+39"),
    ("lreal", math.inf, "symbol s is an lreal: the value must be a finite number, not Infinity"),
    ("bool", 2, "symbol s is a bool: the value must be true/false or 0/1, not 2"),
    ("word", True, "symbol s is a word: the value must be a whole number 0..65535, not true"),
    ("real", "12.5", 'symbol s is a real: the value must be a finite number, |x| <= 3.402823e+38, '
                     'not "12.5"'),
    ("int", None, "symbol s is an int: the value must be a whole number -32768..32767, not null"),
    # A JSON integer past what a double holds (it raised OverflowError through every door).
    ("real", 10**400, "symbol s is a real: the value must be a finite number, "
                      "|x| <= 3.402823e+38, not 1000000000000000000000000000000000000000"),
    ("lreal", -(10**400), "symbol s is an lreal: the value must be a finite number, "
                          "not -100000000000000000000000000000000000000"),
])
def test_a_value_the_type_cannot_take_is_refused_naming_symbol_type_and_range(
        type_name: str, value: object, text: str) -> None:
    with pytest.raises(ValueRefused) as refused:
        accepted(type_name, value, "s")
    assert str(refused.value) == text


@given(st.sampled_from([t for t in SymType if t is not SymType.BOOL]),
       st.floats(allow_nan=False, allow_infinity=False) | st.integers(-(1 << 40), 1 << 40))
def test_what_is_accepted_reads_back_as_itself_once_stored(t: SymType, value: float) -> None:
    try:
        raw = accepted(t.value, value, "x")
    except ValueRefused:
        return
    back = shown(t.value, raw)
    assert accepted(t.value, back, "x") == raw  # the shown value stores the same bits
    if t is not SymType.REAL:
        assert back == value


def force(symbol: str, value: int, id: int = 0) -> ProgramCommand:
    return ProgramCommand(Command.FORCE, symbol=symbol, value=value, id=id)


@pytest.fixture
def bench(tmp_path: Path) -> Bench:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    return Bench(compile_program(tmp_path, PROGRAM))


def test_typed_forces_act_as_bits_and_are_reported_typed(bench: Bench) -> None:
    replies = bench.scan(10, [force("temp", accepted("real", 12.5, "temp"), id=1),
                              force("small", accepted("int", -7, "small"), id=2),
                              force("level", accepted("lreal", -0.25, "level"), id=3)]).replies
    assert [r.message for r in replies] == [
        "force: temp = 12.5 (state RUNNING)", "force: small = -7 (state RUNNING)",
        "force: level = -0.25 (state RUNNING)"]
    assert bench.plc.forces.shown() == {"level": -0.25, "small": -7, "temp": 12.5}
    assert shown("real", bench.get("temp")) == 12.5
    assert shown("int", bench.get("small")) == -7
    bench.set(go=1)
    bench.scan(20)  # the program writes -3 to small; the force wins, level too
    assert shown("int", bench.get("small")) == -7 and shown("dint", bench.get("count")) == -70000
    assert shown("lreal", bench.get("level")) == -0.25


def test_forces_of_bits_a_type_cannot_hold_are_refused(bench: Bench) -> None:
    replies = bench.scan(10, [force("temp", 0x7FC00000, id=1), force("small", -3, id=2),
                              force("big", 1 << 32, id=3)]).replies
    assert [(r.ok, r.message) for r in replies] == [
        (False, "force refused: symbol temp is a real: force it to a finite number, not nan"),
        (False, "force refused: symbol small is an int: a force carries its raw bits "
                "0..65535, not -3"),
        (False, "force refused: symbol big is a udint: force it to 0..4294967295, "
                "not 4294967296"),
    ]
    assert bench.plc.forces.values() == {} and bench.plc.state is PlcState.RUNNING


def test_a_force_is_dropped_when_a_download_changes_the_symbols_type(
        bench: Bench, tmp_path: Path) -> None:
    bench.scan(10, [force("setp", accepted("real", 1.5, "setp"))])
    (tmp_path / "io.yaml").write_text(IO.replace("%MD0\", type: real", "%MD0\", type: dint"),
                                      encoding="utf-8")
    other = compile_program(tmp_path, PROGRAM)
    bench.scan(20, [ProgramCommand(Command.STOP)])
    bench.scan(30, [ProgramCommand(Command.DOWNLOAD, other)])
    assert "setp" not in bench.plc.forces.values()  # its bits would read 1069547520 there


def test_a_scaled_symbol_is_shown_and_given_in_engineering_units() -> None:
    """The board carries the scale as a mapping (Scaling.as_dict): the same numbers either
    way, and a write scaled back to raw as a program's write is (half to even)."""
    scale = {"raw": [0, 27648], "eng": [0.0, 100.0], "unit": "%", "clamp": True}
    assert shown("int", 13824, scale) == 50.0
    assert shown("int", 0xFFFF, scale) == 0.0  # raw -1, clamped to the span
    assert accepted("int", 50.0, "level", scale) == 13824
    assert accepted("int", 117, "level", scale) == 27648  # clamped
    signed = {"raw": [-500, 1500], "eng": [-50.0, 150.0], "unit": "°C"}
    assert shown("int", 0xFFFF - 29, signed) == -3.0  # raw -30 tenths
    assert accepted("int", -3.0, "temperature", signed) == 0xFFFF - 29
    with pytest.raises(ValueRefused, match=r"temperature is scaled \(-50..150 °C on an int\)"):
        accepted("int", 4000.0, "temperature", signed)  # raw 40000: past an int
    with pytest.raises(ValueRefused, match=r"is scaled \(-50..150 °C on a word\)"):
        accepted("word", -60.0, "temperature", signed)  # raw -600: below a word
    with pytest.raises(ValueRefused, match="engineering units"):
        accepted("int", "hot", "temperature", signed)
    assert shown("int", 7, {"raw": "?"}) == 7  # a scale this version cannot read: unscaled
