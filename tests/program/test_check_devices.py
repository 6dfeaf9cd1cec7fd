"""`softplc check` knows the devices without opening them: sim channels against the plant's
sensors and actuators, Modbus parameters and channels; `simulate` refuses what check refuses,
with FILE:LINE, a hint and exit 1, never a traceback."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from softplc.cli import main
from softplc.devices.check import check_devices
from softplc.program.compiler import compile_file
from softplc.program.io_image import parse_io_image

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def misspelt(tmp_path: Path) -> Path:
    """The transport program with `channel: s1_in` (for s1_i) in its symbols file."""
    (tmp_path / "programs").mkdir()
    (tmp_path / "io_images").mkdir()
    shutil.copytree(ROOT / "programs" / "nets", tmp_path / "programs" / "nets")
    shutil.copy(ROOT / "programs" / "transport.yaml", tmp_path / "programs")
    text = (ROOT / "io_images" / "transport.yaml").read_text(encoding="utf-8")
    bad = text.replace('s1_i: {address: "%IX0.0",', 's1_i: {channel: s1_in, address: "%IX0.0",')
    assert bad != text
    (tmp_path / "io_images" / "transport.yaml").write_text(bad, encoding="utf-8")
    return tmp_path


def _line_of(path: Path, needle: str) -> int:
    lines = path.read_text(encoding="utf-8").splitlines()
    return next(i for i, line in enumerate(lines, 1) if needle in line)


def test_check_refuses_a_misspelt_sim_channel_with_a_hint(
        misspelt: Path, capsys: pytest.CaptureFixture[str]) -> None:
    io = misspelt / "io_images" / "transport.yaml"
    expected = (f"{io}:{_line_of(io, 's1_in')}: symbols.s1_i: channel 's1_in' is not a sensor "
                "of plant 'transport' (did you mean 's1_i'?); its sensors: s1_i, s1_o, s2_i, s2_o")
    assert main(["check", str(misspelt / "programs" / "transport.yaml")]) == 1
    assert capsys.readouterr().err.splitlines()[0] == expected
    assert main(["check", str(io)]) == 1  # the symbols file on its own
    assert capsys.readouterr().err.splitlines()[0] == expected


def test_simulate_refuses_it_without_a_traceback(
        misspelt: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", str(misspelt / "programs" / "transport.yaml"),
                 "--duration", "1s"]) == 1
    err = capsys.readouterr().err
    assert "channel 's1_in' is not a sensor" in err and "Traceback" not in err


def test_the_plant_given_with_plant_is_checked(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    program = str(ROOT / "programs" / "transport.yaml")
    assert main(["simulate", program, "--plant", "drilling", "--duration", "1s"]) == 1
    assert "drivers.plant: names plant 'transport', --plant asks for 'drilling'" \
        in capsys.readouterr().err
    # an io image whose sim driver names no plant takes --plant's, checked as its own would be
    text = (ROOT / "io_images" / "transport.yaml").read_text(encoding="utf-8")
    (tmp_path / "io.yaml").write_text(text.replace("{kind: sim, plant: transport}",
                                                   "{kind: sim}"), encoding="utf-8")
    (tmp_path / "p.yaml").write_text("io_image: io.yaml\nplaces: {p: {tokens: 1}}\n"
                                     "transitions: {t: {from: [p], when: s1_i}}\n",
                                     encoding="utf-8")
    assert main(["simulate", str(tmp_path / "p.yaml"), "--plant", "drillng"]) == 1
    err = capsys.readouterr().err
    assert "--plant 'drillng': no such plant model (did you mean 'drilling'?)" in err
    assert main(["simulate", str(tmp_path / "p.yaml"), "--plant", "drilling"]) == 1
    err = capsys.readouterr().err
    assert "channel 'm1' (the symbol's name: no channel: given) is not an actuator of plant " \
           "'drilling'" in err
    assert main(["check", str(tmp_path / "p.yaml"), "--plant", "drilling"]) == 1
    assert "is not an actuator of plant 'drilling'" in capsys.readouterr().err
    assert main(["check", str(tmp_path / "p.yaml")]) == 0  # the plant of a later --plant
    assert main(["simulate", str(tmp_path / "p.yaml")]) == 1
    assert ("a sim driver needs plant: NAME (one of drilling, tank, transport)"
            in capsys.readouterr().err)
    assert main(["simulate", str(tmp_path / "p.yaml"), "--plant", "transport",
                 "--duration", "1s"]) == 0


def test_the_case_studies_and_their_symbols_files_pass(capsys: pytest.CaptureFixture[str]) -> None:
    for name in ("transport", "drilling"):
        assert main(["check", str(ROOT / "programs" / f"{name}.yaml")]) == 0
        assert main(["check", str(ROOT / "io_images" / f"{name}.yaml")]) == 0
    out = capsys.readouterr().out
    assert "symbols " in out and "drivers: plant (sim)" in out


MODBUS_IO = """\
drivers:
  rio: {kind: modbus, host: 127.0.0.1, port: 70000}
  sim: {kind: sim, plant: transport, plnat: x}
symbols:
  a: {address: "%IX0.0", channel: "di-3"}
  b: {address: "%IX0.1", channel: "xx:1"}
  c: {address: "%QX0.0", channel: "di:1"}
  d: {address: "%IW0", channel: "ir:70000"}
  e: {address: "%QW0", channel: "hr:5"}
  f: {address: "%QW1", channel: "hr:5"}
  g: {address: "%IX0.2", driver: sim, channel: s1_o}
"""


def test_modbus_parameters_and_channels_are_checked_without_a_connection() -> None:
    text = MODBUS_IO
    for symbol in "abcdef":
        text = text.replace(f"  {symbol}: {{", f"  {symbol}: {{driver: rio, ")
    problems = [str(p) for p in check_devices(parse_io_image(text, "rio.yaml"))]
    assert problems == [
        "rio.yaml:2: drivers.rio: driver 'rio': port must be an integer in 1..65535",
        "rio.yaml:3: drivers.sim.plnat: unknown key 'plnat' (did you mean 'plant'?); "
        "a sim driver takes: plant",
        "rio.yaml:5: symbols.a: driver rio: channel 'di-3': expected TABLE:OFFSET, e.g. di:0",
        "rio.yaml:6: symbols.b: driver rio: channel 'xx:1': table 'xx' is not coil, di, hr or ir",
        "rio.yaml:7: symbols.c: driver rio: channel 'di:1': a bit output (%QX0.0) expects coil",
        "rio.yaml:8: symbols.d: driver rio: channel 'ir:70000': offset 70000 is not in 0..65535",
        "rio.yaml:10: symbols.f: driver rio: channel 'hr:5' is already used by symbol 'e'",
    ]


def test_a_valid_program_compiles_and_checks_clean() -> None:
    assert check_devices(compile_file(ROOT / "programs" / "drilling.yaml").io) == []
