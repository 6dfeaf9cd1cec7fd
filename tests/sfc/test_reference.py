"""The net a chart compiles to and a reference SFC interpreter written from the standard
(refsfc.py, reading the XML itself) agree scan by scan: on every example chart and on
generated charts, with hypothesis-generated inputs (counts scale with SOFTPLC_FUZZ_SCALE)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from softplc.program.compiler import compile_file
from tests.fuzz.budget import scaled
from tests.sfc.chartxml import ChartSpec, chart_xml
from tests.sfc.compare import compare
from tests.sfc.gencharts import charts, inputs
from tests.sfc.refsfc import RefSfc, read

EXAMPLES = Path(__file__).parent / "examples"
PROGRAMS = Path(__file__).parents[2] / "programs"
FBD = Path(__file__).parent / "fbd"  # conditions wired from FBD/LD networks (not exported)
RUNNABLE = sorted([*EXAMPLES.glob("*.xml"), *FBD.glob("*.xml"), *PROGRAMS.glob("*_sfc.xml")])
# No shrinking: a failure prints its chart (the assertion message) and stays fast.
SETTINGS = settings(max_examples=scaled(15), deadline=None, derandomize=True,
                    phases=[Phase.explicit, Phase.reuse, Phase.generate],
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@pytest.mark.parametrize("path", RUNNABLE, ids=lambda p: p.name)
@SETTINGS
@given(data=st.data())
def test_example_charts_agree_with_the_reference(path: Path, data: st.DataObject) -> None:
    io = compile_file(path).io
    names = [n for n, s in io.symbols.items() if str(s.address).startswith("%I")]
    kinds = {n: st.booleans() if io.symbols[n].type.value == "bool" else st.integers(0, 20)
             for n in names}
    scans = data.draw(st.lists(st.fixed_dictionaries(kinds), min_size=40, max_size=40))
    assert compare(path, scans) is None


@SETTINGS
@given(spec=charts(), scans=inputs(40))
def test_generated_charts_agree_with_the_reference(tmp_path_factory: pytest.TempPathFactory,
                                                   spec: object, scans: list[dict[str, bool]]
                                                   ) -> None:
    path = tmp_path_factory.mktemp("chart") / "chart.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")  # type: ignore[arg-type]
    assert compare(path, scans) is None, spec


def test_two_n_bodies_on_one_step_both_run_every_scan(tmp_path: Path) -> None:
    spec = ChartSpec(["S0", "S1"], ["S0"], [(["S0"], ["S1"], "i0"), (["S1"], ["S0"], "i1")],
                     [("S1", "N", "a"), ("S1", "N", "b")],
                     {"i0": ("BOOL", "%IX0.0"), "i1": ("BOOL", "%IX0.1"),
                      "c0": ("INT", "%QW0"), "c1": ("INT", "%QW1")},
                     {"a": "c0 := c0 + 1;", "b": "c1 := c1 + 2;"})
    path = tmp_path / "two.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    scans = [{"i0": k == 1, "i1": k == 8} for k in range(12)]
    assert compare(path, scans) is None


def test_timed_actions_l_d_ds_agree_with_the_reference(tmp_path: Path) -> None:
    spec = ChartSpec(["S0", "S1", "S2", "S3"], ["S0"],
                     [(["S0"], ["S1"], "i0"), (["S1"], ["S2"], "i1"), (["S2"], ["S3"], "i2"),
                      (["S3"], ["S0"], "TRUE")],
                     [("S1", "L@T#30ms", "q0"), ("S1", "D@T#20ms", "q1"),
                      ("S2", "DS@20ms", "q2"), ("S0", "R", "q2")],
                     {"i0": ("BOOL", "%IX0.0"), "i1": ("BOOL", "%IX0.1"),
                      "i2": ("BOOL", "%IX0.2"), "q0": ("BOOL", "%QX0.0"),
                      "q1": ("BOOL", "%QX0.1"), "q2": ("BOOL", "%QX0.2")})
    path = tmp_path / "timed.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    # S1 held 6 scans (L runs out, D comes on), then 2 (neither runs out); S2 held long
    # enough to store q2 (R in S0), then left in the very scan its timer runs out: no store.
    scans = [{"i0": k in (1, 26), "i1": k in (7, 28), "i2": k in (20, 31)} for k in range(34)]
    assert compare(path, scans) is None
    assert {"S1_L_q0", "S1_D_q1", "S2_DS_q2"} <= set(compile_file(path).place_names)
    ref, seen = RefSfc(read(path.read_text(encoding="utf-8"))), []
    for k, values in enumerate(scans):
        ref.scan(k * 10, values)
        seen.append("".join("1" if ref.env[q] else "0" for q in ("q0", "q1", "q2")))
    assert (seen[2], seen[4], seen[6], seen[15], seen[21], seen[28], seen[31]) == \
        ("100", "110", "010", "001", "000", "000", "000")


def test_stored_timed_actions_sd_sl_agree_with_the_reference(tmp_path: Path) -> None:
    spec = ChartSpec(["S0", "S1", "S2", "S3"], ["S0"],
                     [(["S0"], ["S1"], "i0"), (["S1"], ["S2"], "i1"), (["S2"], ["S1"], "i2"),
                      (["S2"], ["S3"], "i3"), (["S3"], ["S0"], "TRUE")],
                     [("S1", "SD@T#50ms", "q0"), ("S1", "SL@T#40ms", "q1"),
                      ("S3", "R", "q0"), ("S3", "R", "q1")],
                     {f"i{k}": ("BOOL", f"%IX0.{k}") for k in range(4)} |
                     {"q0": ("BOOL", "%QX0.0"), "q1": ("BOOL", "%QX0.1")})
    path = tmp_path / "stored.xml"
    path.write_text(chart_xml(spec), encoding="utf-8")
    # S1 entered at scan 1 and left at 2: both latches outlive it (SL goes off at 6, SD comes
    # on at 7); S1 entered again at 6, while latched and as SL's timer runs out: nothing
    # restarts, SL goes off; R in S3 at 14 cancels both; S1 entered at 17, and R at 20
    # before SD's time: SD never comes on.
    scans = [{"i0": k in (1, 17), "i1": k in (2, 13, 18), "i2": k == 6, "i3": k in (14, 20)}
             for k in range(26)]
    assert compare(path, scans) is None
    ref, seen = RefSfc(read(path.read_text(encoding="utf-8"))), []
    for k, values in enumerate(scans):
        ref.scan(k * 10, values)
        seen.append("".join("1" if ref.env[q] else "0" for q in ("q0", "q1")))
    assert seen[1:9] == ["01"] * 5 + ["00", "10", "10"], seen
    assert (seen[11], seen[14], seen[17], seen[20], seen[22]) == ("10", "00", "01", "00", "00")
