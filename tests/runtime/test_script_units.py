"""Issue 39, item 1: a simulation script gives values as `softplc force` and the API do
(core/present.py: a scaled symbol in engineering units, a real as a real, a 16-bit int as
its signed value; `{raw: N}` for the value before scaling), and the timeline shows them as
the program reads them: an HMI write of a real as its value, not its two registers, and a
scaled value at its scale's resolution, not a double's noise. On programs/tank.yaml."""

from __future__ import annotations

import pytest

from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from softplc.runtime.offline.simscript import parse_script
from softplc.runtime.offline.simulate import format_timeline, simulate

S = 10**9
NET = compile_file("programs/tank.yaml")


def _run(script: str) -> list[dict[str, object]]:
    report = simulate(NET, 3 * S, script=parse_script(script, "s.yaml", NET.io), timeline=True)
    return list(report["timeline"])


def test_a_scaled_input_is_forced_in_engineering_units_and_shown_at_its_resolution() -> None:
    line = _run("- at: 1s\n  force: {level: 47.0, temperature: -10.0}\n")
    forced = [e["forced"] for e in line if "forced" in e]
    # 47.0 % is raw 12994.56 -> 12995 -> 47.0016 %: three decimals tell counts apart
    assert forced == [{"level": 47.002, "temperature": -10.0}]


def test_raw_is_given_only_with_its_marker_and_a_16_bit_int_as_its_signed_value() -> None:
    line = _run("- at: 1s\n  force: {level: {raw: 13824}, temperature: {raw: -100}}\n")
    assert [e["forced"] for e in line if "forced" in e] == [{"level": 50.0,
                                                             "temperature": -10.0}]
    with pytest.raises(ProgramError) as bad:
        parse_script("- at: 1s\n  force: {temperature: {raw: 65436}}\n"
                     "- at: 2s\n  force: {level: {counts: 1}}\n"
                     "- at: 3s\n  force: {temperature: 5000}\n", "s.yaml", NET.io)
    text = str(bad.value)
    assert "s.yaml:2: [0].force.temperature: symbol temperature is an int: the value must " \
           "be a whole number -32768..32767, not 65436" in text
    assert "s.yaml:4: [1].force.level: level: expected a value or {raw: N}" in text
    assert "s.yaml:6: [2].force.temperature: symbol temperature is scaled (-50..150 °C on " \
           "an int): the value must be a finite number in engineering units" in text


def test_the_timeline_shows_an_hmi_write_of_a_real_as_its_value() -> None:
    line = _run("- at: 1s\n  write: {fill_to: 50.0, min_temp: -1.5}\n")
    writes = [e for e in line if "hmi" in e]
    assert writes[0]["hmi"] == ["fill_to=50.0", "min_temp=-1.5"]
    text = "\n".join(format_timeline(line))
    assert "hmi write fill_to=50.0, min_temp=-1.5 | fill_to=50.0, min_temp=-1.5" in text
    assert "16968" not in text
