"""Issue 39, item 1 in an error message: a replay that differs names the output symbols with
their values as the program reads them (core/present.py): a real as a real, a scaled output
in engineering units with its unit, not their bits or raw counts."""

from __future__ import annotations

from pathlib import Path

from softplc.debug.replay import replay
from softplc.program.compiler import compile_file
from softplc.runtime.offline.simulate import simulate

IO = """\
symbols:
  flow:  {address: "%QD0", type: real}
  valve: {address: "%QW0", type: int, scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: "%"}}
"""
PROGRAM = """\
program: p
io_image: io.yaml
places:
  idle: {tokens: 1}
  on: {}
transitions:
  go: {from: [idle], to: [on], do: ["flow = FLOW", "valve = 40.0"]}
"""


def test_a_replay_mismatch_shows_a_real_as_a_real_and_a_scaled_output_with_its_unit(
        tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "p.yaml").write_text(PROGRAM.replace("FLOW", "2.5"), encoding="utf-8")
    trace = tmp_path / "t.jsonl"
    simulate(compile_file(tmp_path / "p.yaml"), 10**8, trace_path=trace)
    (tmp_path / "p.yaml").write_text(PROGRAM.replace("FLOW", "1.5").replace(
        "valve = 40.0", "valve = 40.5"), encoding="utf-8")
    result = replay(trace, compile_file(tmp_path / "p.yaml"))
    assert result.divergence is not None, "the changed program replayed the trace"
    assert "differs: flow recorded 2.5, replay 1.5; valve recorded 39.999 %, replay " \
           "40.498 %" in result.divergence  # raw 11059 and 11197: counts, result.divergence
