"""`init:` on memory symbols and `scale: {modbus: ...}` in a symbols file (issue 30): every
wrong value is a problem at its line, found by `softplc check`, naming what was expected; a
good one is stored as the raw bits it puts in the image; both enter the program hash only
where declared."""

from __future__ import annotations

import struct
from pathlib import Path

import pytest

from softplc.cli import main
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.program.io_image import parse_io_image

TRAP = "is text here, not a boolean: write true or false"
BAD = """symbols:
  lamp:   {address: "%QX0.0", init: true}
  sensor: {address: "%IX0.0", init: false}
  sp:     {address: "%MW0", init: 70000}
  frac:   {address: "%MW1", init: 1.5}
  flag:   {address: "%MX0.0", init: on}
  level:  {address: "%MW2", type: int, init: 101,
           scale: {raw: [0, 27648], eng: [0, 100], clamp: true}}
  far:    {address: "%MW3", type: int, init: 150, scale: {raw: [0, 27648], eng: [0, 100]}}
  text:   {address: "%MW4", init: "fifty"}
  nan:    {address: "%MD0", type: real, init: .nan}
  shown:  {address: "%MW5", type: int, scale: {raw: [0, 27648], eng: [0, 100], modbus: engg}}
"""
EXPECTED = [
    "{F}:2: symbols.lamp.init: init applies to memory symbols (%M) only, not out: an output's "
    "value is the program's while it runs and its `safe:` value otherwise",
    "{F}:3: symbols.sensor.init: init applies to memory symbols (%M) only, not in: an input's "
    "value comes from its driver at every scan",
    "{F}:4: symbols.sp.init: init 70000 refused: symbol sp is a word: the value must be a whole "
    "number 0..65535, not 70000",
    "{F}:5: symbols.frac.init: init 1.5 refused: symbol frac is a word: the value must be a "
    "whole number 0..65535, not 1.5",
    "{F}:6: symbols.flag.init: init 'on' refused: symbol flag is a bool: the value must be "
    f"true/false or 0/1, not \"on\" ('on' {TRAP})",
    "{F}:7: symbols.level.init: init 101 is outside the scale's eng span [0, 100] (clamp: true "
    "would store its end instead)",
    "{F}:9: symbols.far.init: init 150 refused: symbol far is scaled (0..100 on an int): the "
    "value must be a finite number in engineering units that scales into the int's range, "
    "not 150",
    "{F}:10: symbols.text.init: init 'fifty' refused: symbol text is a word: the value must be "
    "a whole number 0..65535, not \"fifty\"",
    "{F}:11: symbols.nan.init: init nan refused: symbol nan is a real: the value must be a "
    "finite number, |x| <= 3.402823e+38, not NaN",
    "{F}:12: symbols.shown.scale.modbus: modbus 'engg': expected raw (the Modbus slave serves "
    "the raw value, the default) or eng (the engineering value, in the symbol's type) "
    "(did you mean 'eng'?)",
]


def test_every_bad_init_is_a_problem_at_its_line_with_what_was_expected(tmp_path: Path) -> None:
    path = tmp_path / "io.yaml"
    with pytest.raises(ProgramError) as caught:
        parse_io_image(BAD, str(path))
    assert [str(p) for p in caught.value.problems] == [
        line.replace("{F}", str(path)) for line in EXPECTED]


def test_softplc_check_reports_them_and_fails(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "io.yaml"
    path.write_text(BAD, encoding="utf-8")
    assert main(["check", str(path)]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err == [line.replace("{F}", str(path)) for line in EXPECTED] + [
        f"{path}: {len(EXPECTED)} problem(s)"]


def test_a_good_init_is_kept_as_the_raw_bits_it_stores() -> None:
    io = parse_io_image("""symbols:
  count:  {address: "%MW0", init: 12}
  small:  {address: "%MW1", type: int, init: -3}
  hold:   {address: "%MX0.0", init: true}
  level:  {address: "%MW2", type: int, init: 50.0,
           scale: {raw: [0, 27648], eng: [0.0, 100.0], modbus: eng}}
  ratio:  {address: "%MD0", type: real, init: 0.1}
  big:    {address: "%ML0", type: lreal, init: -1.0e+300}
  whole:  {address: "%MW3", init: 4.0}
  none:   {address: "%MW4"}
""", "io.yaml")
    raw = {name: sym.init_raw for name, sym in io.symbols.items()}
    assert raw == {"count": 12, "small": 0xFFFD, "hold": 1, "level": 13824,
                   "ratio": struct.unpack("<I", struct.pack("<f", 0.1))[0],
                   "big": struct.unpack("<Q", struct.pack("<d", -1e300))[0], "whole": 4,
                   "none": None}
    scaling = io.symbols["level"].scaling
    assert scaling is not None and scaling.modbus == "eng"
    assert scaling.as_dict()["modbus"] == "eng"


@pytest.mark.parametrize(("before", "after", "same"), [
    ("{address: '%MW0'}", "{address: '%MW0', init: 5}", False),
    ("{address: '%MW0', init: 5}", "{address: '%MW0', init: 6}", False),
    ("{address: '%MW0', init: 5}", "{address: '%MW0', init: 5, retain: none}", True),
    ("{address: '%MW0', type: int, scale: {raw: [0, 100], eng: [0, 1]}}",
     "{address: '%MW0', type: int, scale: {raw: [0, 100], eng: [0, 1], modbus: eng}}", False),
    ("{address: '%MW0', type: int, scale: {raw: [0, 100], eng: [0, 1]}}",
     "{address: '%MW0', type: int, scale: {raw: [0, 100], eng: [0, 1], modbus: raw}}", True),
])
def test_init_and_modbus_eng_enter_the_program_hash_where_declared(
        tmp_path: Path, before: str, after: str, same: bool) -> None:
    """A trace records the program hash; what the PLC does differently must change it
    (`retain:` alone does not: a warm start stays possible, docs/retain.md)."""
    program = tmp_path / "p.yaml"
    program.write_text("program: p\nio_image: io.yaml\nplaces: {idle: {tokens: 1}}\n",
                       encoding="utf-8")
    hashes = []
    for symbol in (before, after):
        (tmp_path / "io.yaml").write_text(f"symbols:\n  sp: {symbol}\n", encoding="utf-8")
        hashes.append(compile_file(program).program_hash)
    assert (hashes[0] == hashes[1]) is same


DOCS = Path(__file__).resolve().parents[2] / "docs"


def _block(page: str, heading: str, fence: str) -> str:
    """The first ```fence block after `heading` in docs/`page`."""
    text = (DOCS / page).read_text(encoding="utf-8")
    after = text[text.index(heading):]
    return after.split(f"```{fence}\n", 1)[1].split("```", 1)[0]


def test_the_documented_examples_hold() -> None:
    init = parse_io_image(_block("programs.md", "### Initial values", "yaml"), "io.yaml")
    assert {name: sym.init_raw for name, sym in init.symbols.items()} == {
        "fill_to": 0x42A00000, "min_temp": 0x40000000, "auto": 1, "speed_sp": 13824}
    modbus = parse_io_image(_block("modbus.md", "### Scaled symbols: raw or engineering units",
                                   "yaml"), "io.yaml")
    shown = {name: sym.scaling.modbus for name, sym in modbus.symbols.items() if sym.scaling}
    assert shown == {"level": "eng", "level_raw": "raw", "setpoint": "eng", "flow": "eng"}
    assert modbus.symbols["setpoint"].init_raw == 22118  # 80 % of 27648 = 22118.4
    # every problem the page shows is one `softplc check` gives for the lines above
    documented = _block("programs.md", "### Initial values", "text").splitlines()
    produced = [line.replace("{F}", "io.yaml") for line in EXPECTED]
    assert documented and set(documented) <= set(produced)
