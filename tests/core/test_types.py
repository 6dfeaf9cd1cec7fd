"""Types beyond bool and word (issue 30): int, dint, udint, real, lreal in the io image, in
expressions, in writes, in events; NaN, overflow and division by zero as located diagnostics;
real results bit for bit the same in every run."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.core.datatypes import SymType, TypeRangeError, convert, raw_of, stored, value_of
from softplc.core.expr import NameKind, Scope, compile_expr
from softplc.core.image import ProcessImage
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_file
from tests.core.helpers import Ctx

IO = """\
symbols:
  temp:   {address: "%IW0", type: int, driver: none}
  level:  {address: "%ID0", type: real, driver: none}
  flow:   {address: "%IL0", type: lreal, driver: none}
  count:  {address: "%MD0", type: dint}
  total:  {address: "%MD1", type: udint}
  avg:    {address: "%MD2", type: real}
  big:    {address: "%ML0", type: lreal}
  small:  {address: "%MW0", type: int}
  out:    {address: "%QD0", type: real, safe: -1.5}
events:
  cold:   {below: temp, threshold: -5, hysteresis: 2}
  high:   {above: level, threshold: 80.5, hysteresis: 0.5}
  moved:  {change: flow}
"""


def build(tmp_path: Path, transitions: str, io: str = IO) -> object:
    (tmp_path / "io.yaml").write_text(io)
    text = ("program: typed\nio_image: io.yaml\nplaces:\n  p: {tokens: 1}\n  q: {}\n"
            f"transitions:\n{transitions}")
    (tmp_path / "prog.yaml").write_text(text)
    return compile_file(tmp_path / "prog.yaml")


class Run:
    """A PLC with the typed program, inputs set by value (encoded as the image holds them)."""

    def __init__(self, tmp_path: Path, transitions: str) -> None:
        from softplc.core.lifecycle import Command
        from softplc.core.plc import Plc, ProgramCommand
        from softplc.core.scan import scan
        self.net = build(tmp_path, transitions)
        self._scan, self._cmd = scan, ProgramCommand
        self.plc = Plc.empty(ProcessImage(self.net.io.sizes))  # type: ignore[attr-defined]
        self.inputs = ProcessImage(self.net.io.sizes)  # type: ignore[attr-defined]
        self.result = scan(self.plc, self.inputs, 0, [ProgramCommand(Command.DOWNLOAD, self.net),
                                                       ProgramCommand(Command.START)])
        self.t = 0

    def set(self, **values: float) -> None:
        for name, value in values.items():
            sym = self.net.io.symbols[name]  # type: ignore[attr-defined]
            self.inputs.set(sym.address, raw_of(sym.type, stored(sym.type, value)))

    def step(self) -> object:
        self.t += 1_000_000
        self.result = self._scan(self.plc, self.inputs, self.t)
        return self.result

    def get(self, name: str) -> float:
        sym = self.net.io.symbols[name]  # type: ignore[attr-defined]
        return value_of(sym.type, self.plc.image.get(sym.address))

    def diagnostics(self) -> list[str]:
        return self.plc.engine.diagnostics if self.plc.engine else []


# -- the codec ----------------------------------------------------------------------------------

@pytest.mark.parametrize(("t", "value", "raw"), [
    (SymType.INT, -1, 0xFFFF),
    (SymType.INT, -32768, 0x8000),
    (SymType.DINT, -2, 0xFFFFFFFE),
    (SymType.UDINT, 4_000_000_000, 4_000_000_000),
    (SymType.REAL, 1.5, 0x3FC00000),
    (SymType.LREAL, -2.5, struct.unpack("<Q", struct.pack("<d", -2.5))[0]),
])
def test_values_are_stored_as_their_bits(t: SymType, value: float, raw: int) -> None:
    assert raw_of(t, stored(t, value)) == raw
    assert value_of(t, raw) == value


@pytest.mark.parametrize(("t", "value", "message"), [
    (SymType.INT, 32768, "32768 is out of range of int (-32768..32767)"),
    (SymType.WORD, -1, "-1 is out of range of word (0..65535)"),
    (SymType.DINT, 1 << 31, "out of range of dint"),
    (SymType.UDINT, -1, "out of range of udint"),
    (SymType.REAL, 1e39, "out of range of real"),
    (SymType.LREAL, math.nan, "the result is NaN"),
    (SymType.REAL, math.inf, "the result is infinite"),
    (SymType.DINT, 2.5, "the fraction 2.5 cannot be written to a dint symbol without a "
                        "conversion"),
])
def test_a_write_that_does_not_fit_raises_never_wraps(t: SymType, value: float,
                                                      message: str) -> None:
    with pytest.raises((TypeRangeError, TypeError), match=message.replace("(", r"\(")
                       .replace(")", r"\)")):
        stored(t, value)


def test_real_to_int_rounds_half_to_even_and_trunc_cuts() -> None:
    assert [convert(SymType.INT, v) for v in (0.5, 1.5, 2.5, -0.5, -1.5, 2.4999)] == \
        [0, 2, 2, 0, -2, 2]
    scope = Scope({"r": NameKind.REAL})
    assert compile_expr("trunc(-2.7)", scope)(Ctx()) == -2
    assert compile_expr("dint(r)", scope)(Ctx({"r": 7.5})) == 8  # type: ignore[dict-item]
    with pytest.raises(TypeRangeError):
        compile_expr("int(40000.0)", scope)(Ctx())


def test_real_rounds_to_single_precision() -> None:
    assert stored(SymType.REAL, 0.1) == float(np.float32(0.1)) != 0.1
    assert compile_expr("real(0.1)", Scope({}))(Ctx()) == float(np.float32(0.1))


@pytest.mark.parametrize(("text", "error"), [
    ("1.0 / 0", ZeroDivisionError),
    ("7 // 0", ZeroDivisionError),
    ("2.5 % 0", ZeroDivisionError),
    ("1e308 * 10", TypeRangeError),
    ("2.5 & 1", TypeError),
])
def test_arithmetic_errors_are_raised_not_returned(text: str, error: type[Exception]) -> None:
    with pytest.raises(error):
        compile_expr(text, Scope({}))(Ctx())


def test_mixed_arithmetic_and_comparisons() -> None:
    scope = Scope({"r": NameKind.REAL, "i": NameKind.WORD})
    ctx = Ctx({"r": 2.5, "i": -3})  # type: ignore[dict-item]
    assert compile_expr("r * i", scope)(ctx) == -7.5
    assert compile_expr("i / 2", scope)(ctx) == -1.5  # / is true division: a real
    assert compile_expr("i // 2", scope)(ctx) == -2
    assert compile_expr("r > i and r <= 2.5", scope)(ctx) is True
    assert compile_expr("max(r, i)", scope)(ctx) == 2.5


# -- the io image -------------------------------------------------------------------------------

@pytest.mark.parametrize(("symbol", "message"), [
    ('{address: "%MD0", type: float}',
     "symbols.x.type: unknown type 'float'; expected one of bool, int, word, dint, udint, real, "
     "lreal"),
    ('{address: "%IW3", type: real}',
     "symbols.x.type: type real does not fit address %IW3 (a 16-bit word address holds int or "
     "word; a real needs a %ID address, e.g. %ID0)"),
    ('{address: "%QL0", type: dint}', "type dint does not fit address %QL0"),
    ('{address: "%QW0", type: int, safe: 40000}',
     "symbols.x.safe: safe value of an int must be a whole number -32768..32767"),
    ('{address: "%MD999"}', "address %MD999 is outside the image (size 256)"),
])
def test_bad_symbols_are_located(tmp_path: Path, symbol: str, message: str) -> None:
    io = f"symbols:\n  x: {symbol}\n"
    with pytest.raises(ProgramError) as err:
        build(tmp_path, "  t: {from: [p], to: [q]}\n", io)
    [found] = [str(p) for p in err.value.problems]
    assert found.startswith(f"{tmp_path / 'io.yaml'}:2: symbols.x."), found
    assert found.endswith(message) or message in found, found


def test_a_real_written_to_an_integer_symbol_needs_a_conversion(tmp_path: Path) -> None:
    with pytest.raises(ProgramError) as err:
        build(tmp_path, '  t: {from: [p], to: [q], do: ["count = level * 2"]}\n')
    assert [p.message for p in err.value.problems] == [
        "count is dint: 'level * 2' gives a real; convert it (dint(x) rounds half to even, "
        "trunc(x) cuts toward zero)"]
    build(tmp_path, '  t: {from: [p], to: [q], do: ["count = dint(level * 2)"]}\n')


# -- the scan -----------------------------------------------------------------------------------

def test_typed_values_flow_through_the_scan(tmp_path: Path) -> None:
    run = Run(tmp_path, '  t: {from: [p], to: [q], when: "temp < 0 and level > 50.25", '
                        'do: ["count = temp * 1000", "avg = level / 3", "big = flow * 2", '
                        '"small = temp", "out = level"]}\n')
    run.set(temp=-12, level=75.5, flow=0.1)
    run.step()
    assert run.result.fired == ("t",)  # type: ignore[attr-defined]
    assert (run.get("count"), run.get("small"), run.get("out")) == (-12000, -12, 75.5)
    assert run.get("avg") == float(np.float32(75.5 / 3))
    assert run.get("big") == 0.1 * 2


@pytest.mark.parametrize(("action", "why"), [
    ("small = temp * 10000", "-120000 is out of range of int (-32768..32767)"),
    ("avg = level - level * 0 + 1e300 * 1e10", "the result is infinite"),
    ("count = dint(level / (temp + 12))", "division by zero"),
    ("total = temp", "-12 is out of range of udint"),
])
def test_a_bad_write_is_a_located_diagnostic_and_not_done(tmp_path: Path, action: str,
                                                          why: str) -> None:
    run = Run(tmp_path, f'  t: {{from: [p], to: [q], when: "level > 0", do: ["{action}"]}}\n')
    run.set(temp=-12, level=75.5)
    before = run.plc.image.outputs_bytes()
    run.step()
    assert run.result.fired == ("t",)  # type: ignore[attr-defined]
    assert run.plc.image.outputs_bytes() == before
    [message] = run.diagnostics()
    assert f"{tmp_path / 'prog.yaml'}:7: transition t: " in message  # file:line of t
    assert why in message


def test_nan_from_an_input_is_a_diagnostic(tmp_path: Path) -> None:
    run = Run(tmp_path, '  t: {from: [p], to: [q], when: "level != 0", do: ["avg = level + 1"]}\n')
    level = run.net.io.symbols["level"]  # type: ignore[attr-defined]
    run.inputs.set(level.address, 0x7FC00000)  # a device delivered a NaN
    run.step()
    assert run.get("avg") == 0.0
    assert "the result is NaN" in run.diagnostics()[0]


def test_events_on_signed_and_real_symbols(tmp_path: Path) -> None:
    run = Run(tmp_path, "  t: {from: [p], to: [q], when: cold and high}\n")
    run.set(temp=3, level=10.0, flow=1.0)
    run.step()
    run.set(temp=-6, level=80.75, flow=1.5)
    result = run.step()
    assert set(result.events) >= {"cold", "high", "moved"}  # type: ignore[attr-defined]
    run.set(temp=-4, level=80.25)  # inside the hysteresis bands: no re-arm, no event
    run.step()
    run.set(temp=-6, level=80.75)
    assert not set(run.step().events) & {"cold", "high"}  # type: ignore[attr-defined]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e6, 1e6, width=32), st.integers(-300, 300)),
                min_size=1, max_size=12))
def test_real_results_are_bit_identical_across_runs(inputs: list[tuple[float, int]]) -> None:
    """Two PLCs fed the same inputs give the same images, bit for bit, and each real result
    is the float32 rounding of the double-precision expression (numpy as the reference)."""
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        body = ('  t: {from: [p], to: [p], do: ["avg = level * 1.1 + temp / 7", '
                '"big = big + level / 3", "count = dint(level) % 1000"]}\n')
        a, b = Run(Path(tmp), body), Run(Path(tmp), body)
        big = 0.0
        for level, temp in inputs:
            for run in (a, b):
                run.set(level=level, temp=temp)
                run.step()
            assert a.plc.image.outputs_bytes() == b.plc.image.outputs_bytes()
            expected = np.float32(np.float64(np.float32(level)) * 1.1 + temp / 7)
            assert a.plc.image.md[2] == expected.view(np.uint32)
            big = big + float(np.float32(level)) / 3
            assert a.get("big") == big
