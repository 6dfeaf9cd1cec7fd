"""Scaling per symbol (issue 30, item 2): raw device values <-> engineering units.

The pure map first (core/scaling.py), then the symbols file's `scale:` with located problems,
then the scan: guards and events read engineering values, writes store raw values, and the
same inputs give the same images bit for bit in the scan, `simulate` and `replay`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.core.datatypes import TypeRangeError
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.problems import ProgramError
from softplc.core.scaling import Scaling
from softplc.core.scan import scan
from softplc.program.compiler import compile_file

PCT = Scaling((0, 27648), (0.0, 100.0), "%", clamp=True)

# -- the map ------------------------------------------------------------------------------------


def test_the_ends_map_exactly_and_the_middle_linearly() -> None:
    assert (PCT.to_eng(0), PCT.to_eng(27648), PCT.to_eng(13824)) == (0.0, 100.0, 50.0)
    odd = Scaling((5530, 27648), (0.1, 0.3))  # 4..20 mA; ends a double cannot hold exactly
    assert (odd.to_eng(5530), odd.to_eng(27648)) == (0.1, 0.3)
    assert (odd.to_raw(0.1), odd.to_raw(0.3)) == (5530, 27648)
    backwards = Scaling((0, 1000), (100.0, 0.0))
    assert (backwards.to_eng(250), backwards.to_raw(75.0)) == (75.0, 250)


def test_clamp_limits_reads_and_writes_to_the_span_without_it_extrapolates() -> None:
    assert PCT.to_eng(32511) == 100.0 and PCT.to_eng(-100) == 0.0
    assert PCT.to_raw(117.0) == 27648 and PCT.to_raw(-5.0) == 0
    free = Scaling((0, 27648), (0.0, 100.0))
    assert free.to_eng(32511) == pytest.approx(117.59, abs=0.01)
    assert free.to_raw(110.0) == 30413  # 30412.8, beyond the span: a raw int still holds it


def test_raw_is_rounded_half_to_even() -> None:
    s = Scaling((0, 10), (0.0, 10.0))
    assert [s.to_raw(x) for x in (0.5, 1.5, 2.5, -0.5, 2.4999)] == [0, 2, 2, 0, 2]
    assert Scaling((0.0, 20.0), (0.0, 100.0), whole=False).to_raw(12.5) == 2.5


@pytest.mark.parametrize(("value", "error"), [
    (float("nan"), TypeRangeError), (float("inf"), TypeRangeError), ("x", TypeError)])
def test_nan_infinity_and_text_are_refused(value: object, error: type[Exception]) -> None:
    with pytest.raises(error):
        PCT.to_raw(value)


@settings(max_examples=200, deadline=None)
@given(st.integers(-32768, 32767), st.integers(-32768, 32767), st.integers(-32768, 32767),
       st.floats(-1e6, 1e6), st.floats(-1e6, 1e6))
def test_a_raw_value_read_and_written_back_is_the_same_raw_value(
        r0: int, r1: int, raw: int, e0: float, e1: float) -> None:
    if r0 == r1 or abs(e1 - e0) < 1e-3:
        return
    s = Scaling((r0, r1), (e0, e1))
    assert s.to_raw(s.to_eng(raw)) == raw


# -- the symbols file ---------------------------------------------------------------------------

IO = """\
symbols:
  level:  {address: "%IW0", type: int, driver: none,
           scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%', clamp: true}}
  valve:  {address: "%QW0", type: int, safe: 25.0,
           scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%', clamp: true}}
  temp:   {address: "%IW1", type: word, driver: none,
           scale: {raw: [0, 4000], eng: [-50.0, 150.0], unit: degC}}
  setp:   {address: "%MW0", type: int, scale: {raw: [0, 1000], eng: [0, 100]}}
  heat:   {address: "%QX0.0"}
events:
  high:   {above: level, threshold: 80.5, hysteresis: 0.5}
  warm:   {change: temp}
"""


def build(tmp: Path, transitions: str, io: str = IO) -> CompiledNet:
    (tmp / "io.yaml").write_text(io)
    (tmp / "prog.yaml").write_text("program: scaled\nio_image: io.yaml\nplaces:\n"
                                   f"  p: {{tokens: 1}}\n  q: {{}}\ntransitions:\n{transitions}")
    return compile_file(tmp / "prog.yaml")


@pytest.mark.parametrize(("scale", "line", "message"), [
    ("{raw: [100, 100], eng: [0, 1]}", 3, "symbols.x.scale.raw: raw span is zero (100 to 100)"),
    ("{raw: [0, 100], eng: [a, 1]}", 3, "symbols.x.scale.eng: eng must be two numbers"),
    ("{raw: [0, 100], eng: [0, 1], unit: 5}", 3, "symbols.x.scale.unit: unit must be text"),
    ("{raw: [0, 40000], eng: [0, 1]}", 3, "raw [0, 40000] is out of range of int"),
    ("{raw: [0, 100], eng: [0, 1], clamp: yes}", 3, "symbols.x.scale.clamp: clamp must be"),
    ("{raw: [0, 100], eng: [0, 1], units: '%'}", 3, "unknown key 'units'"),
    ("{raw: [0, 100]}", 3, "symbols.x.scale: expected {raw:"),
])
def test_a_bad_scale_is_located(tmp_path: Path, scale: str, line: int, message: str) -> None:
    io = f'symbols:\n  x: {{address: "%IW0", type: int, driver: none,\n      scale: {scale}}}\n'
    with pytest.raises(ProgramError) as err:
        build(tmp_path, "  t: {from: [p], to: [q]}\n", io)
    [found] = [str(p) for p in err.value.problems]
    assert found.startswith(f"{tmp_path / 'io.yaml'}:{line}: "), found
    assert message in found, found


def test_a_scaled_bool_is_a_located_problem(tmp_path: Path) -> None:
    io = ('symbols:\n  x: {address: "%IX0.0", driver: none,\n'
          '      scale: {raw: [0, 1], eng: [0, 1]}}\n')
    with pytest.raises(ProgramError) as err:
        build(tmp_path, "  t: {from: [p], to: [q]}\n", io)
    [found] = [str(p) for p in err.value.problems]
    assert f"{tmp_path / 'io.yaml'}:3: symbols.x.scale: a bool cannot be scaled" in found


def test_the_symbol_carries_its_scaling_and_a_raw_safe_value(tmp_path: Path) -> None:
    net = build(tmp_path, "  t: {from: [p], to: [q]}\n")
    valve = net.io.symbols["valve"]
    assert valve.scaling == Scaling((0, 27648), (0.0, 100.0), "%", True)
    assert valve.scaling.as_dict() == {"raw": [0, 27648], "eng": [0.0, 100.0], "unit": "%",
                                       "clamp": True}
    assert valve.safe == 6912 and valve.safe_raw == 6912  # 25 % of 27648


def test_a_real_expression_may_be_written_to_a_scaled_integer_symbol(tmp_path: Path) -> None:
    build(tmp_path, '  t: {from: [p], to: [q], do: ["valve = level * 0.5"]}\n')


def test_the_program_hash_changes_with_the_scale(tmp_path: Path) -> None:
    a = build(tmp_path, "  t: {from: [p], to: [q]}\n").program_hash
    b = build(tmp_path, "  t: {from: [p], to: [q]}\n",
              IO.replace("eng: [-50.0, 150.0]", "eng: [-40.0, 150.0]")).program_hash
    assert a != b


# -- the scan -----------------------------------------------------------------------------------

class Run:
    def __init__(self, net: CompiledNet) -> None:
        self.net = net
        self.plc = Plc.empty(ProcessImage(net.io.sizes))
        self.inputs = ProcessImage(net.io.sizes)
        self.t = 0
        self.result = scan(self.plc, self.inputs, 0, [ProgramCommand(Command.DOWNLOAD, net),
                                                      ProgramCommand(Command.START)])

    def raw(self, **values: int) -> None:
        for name, value in values.items():
            self.inputs.set(self.net.io.symbols[name].address, value)

    def step(self) -> object:
        self.t += 1_000_000
        self.result = scan(self.plc, self.inputs, self.t)
        return self.result

    def get(self, name: str) -> int:
        return self.plc.image.get(self.net.io.symbols[name].address)


def test_guards_read_engineering_units_and_writes_store_raw(tmp_path: Path) -> None:
    run = Run(build(tmp_path, '  t: {from: [p], to: [q], when: "level > 50.0 and temp < 0", '
                              'do: ["valve = level / 2", "setp = temp + 60"]}\n'))
    assert run.get("valve") == 0  # RUNNING: the program's own value, not the safe raw 6912
    run.raw(level=13824, temp=1000)  # 50.0 % (not above), 0.0 degC
    run.step()
    assert run.result.fired == ()  # type: ignore[attr-defined]
    run.raw(level=20736, temp=900)  # 75.0 %, -5.0 degC
    run.step()
    assert run.result.fired == ("t",)  # type: ignore[attr-defined]
    assert run.get("valve") == 10368  # 37.5 % of 27648
    assert run.get("setp") == 550  # 55.0 of 0..100 over raw 0..1000


def test_a_write_clamps_or_is_a_located_diagnostic(tmp_path: Path) -> None:
    run = Run(build(tmp_path, '  t: {from: [p], to: [q], when: "level > 1", '
                              'do: ["valve = level * 10", "setp = temp * 100"]}\n'))
    run.raw(level=27648, temp=4000)  # 100 % and 150 degC
    run.step()
    assert run.get("valve") == 27648  # clamp: 1000 % is 100 %
    assert run.get("setp") == 0  # no clamp: 15000 -> raw 150000 > int: not written
    [message] = run.plc.engine.diagnostics if run.plc.engine else []
    assert f"{tmp_path / 'prog.yaml'}:7: transition t: setp = 'temp * 100' failed" in message
    assert "150000 is out of range of int" in message


def test_moore_values_of_a_scaled_output_are_engineering_units(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO)
    (tmp_path / "prog.yaml").write_text(
        "program: scaled\nio_image: io.yaml\nplaces:\n  p: {tokens: 1, outputs: {valve: 50}}\n"
        "  q: {}\ntransitions:\n  t: {from: [p], to: [q], when: heat}\n")
    run = Run(compile_file(tmp_path / "prog.yaml"))
    run.step()
    assert run.get("valve") == 13824


def test_events_compare_engineering_values(tmp_path: Path) -> None:
    run = Run(build(tmp_path, "  t: {from: [p], to: [q], when: high}\n"))
    run.raw(level=22256, temp=100)  # 80.50 %: not above
    assert "high" not in run.step().events  # type: ignore[attr-defined]
    run.raw(level=22258, temp=101)  # 80.507 %
    result = run.step()
    assert {"high", "warm"} <= set(result.events)  # type: ignore[attr-defined]


SIM_IO = """\
symbols:
  raw_in: {address: "%MW0", type: int, scale: {raw: [0, 27648], eng: [-12.5, 87.25]}}
  out:    {address: "%MW1", type: int, scale: {raw: [0, 27648], eng: [0.0, 100.0], clamp: true}}
  acc:    {address: "%MD0", type: real}
"""


def _simulated(tmp: Path, body: str, writes: list[int]) -> tuple[dict[str, object], bool]:
    from softplc.debug.replay import replay
    from softplc.runtime.offline.simscript import load_script
    from softplc.runtime.offline.simulate import simulate
    (tmp / "io.yaml").write_text(SIM_IO)
    (tmp / "prog.yaml").write_text(f"program: sim\nio_image: io.yaml\nplaces:\n  p: {{tokens: 1}}\n"
                                   f"transitions:\n{body}")
    (tmp / "script.yaml").write_text("".join(  # {raw: N}: an int's raw value, signed
        f"- at: {k * 10}ms\n  write: {{raw_in: {{raw: {v - 65536 * (v > 32767)}}}}}\n"
        for k, v in enumerate(writes)))
    net = compile_file(tmp / "prog.yaml")
    script = load_script(tmp / "script.yaml", net.io)
    trace = tmp / "t.jsonl"
    report = simulate(net, (len(writes) + 1) * 10_000_000, period_ns=10_000_000, script=script,
                      trace_path=trace)
    return report, replay(trace, net).ok


BODY = '  t: {from: [p], to: [p], do: ["out = raw_in * 1.37 - 3", "acc = acc + raw_in / 7"]}\n'


@settings(max_examples=15, deadline=None)
@given(st.lists(st.integers(0, 65535), min_size=1, max_size=6))
def test_scaled_results_are_bit_identical_in_scan_simulate_and_replay(writes: list[int]) -> None:
    """Two simulations of the same script give the same report, their traces replay bit for
    bit, and a plain scan fed the same raw values ends with the same image."""
    with tempfile.TemporaryDirectory() as tmp_a, tempfile.TemporaryDirectory() as tmp_b:
        a, a_ok = _simulated(Path(tmp_a), BODY, writes)
        b, b_ok = _simulated(Path(tmp_b), BODY, writes)
        assert a_ok and b_ok
        assert a["outputs_final"] == b["outputs_final"]
        run = Run(compile_file(Path(tmp_a) / "prog.yaml"))
        sym = run.net.io.symbols
        scaling = sym["raw_in"].scaling
        assert scaling is not None
        acc = run.plc.image.md[:1].view(np.float32)[0]  # the start's round fired once
        for raw in writes:
            run.plc.image.set(sym["raw_in"].address, raw)  # memory: the HMI's way in
            run.step()
            eng = scaling.to_eng(raw - 65536 if raw > 32767 else raw)  # an int's bits
            acc = np.float32(float(acc) + eng / 7)
            assert run.plc.image.md[0] == acc.view(np.uint32)
            out = sym["out"].scaling
            assert out is not None
            assert run.get("out") == out.to_raw(eng * 1.37 - 3) & 0xFFFF
