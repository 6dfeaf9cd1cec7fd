"""Every finding points at a real line (issue 39): a finding about the whole net (a deadlock
with every place empty, more deadlocks than listed, an incomplete analysis) at the PNML <net>
element or the program's first line, never line 0; and `check`'s verdict says its budget."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from softplc.analysis.analyze import DEFAULT_MAX_STATES, analyze
from softplc.analysis.gate import verdict_of, verify
from softplc.analysis.pnml import load_for_analysis
from softplc.cli import main
from softplc.program.compiler import compile_file

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent

DEAD_RING = """<?xml version="1.0" encoding="UTF-8"?>
<pnml xmlns="http://www.pnml.org/version-2009/grammar/pnml">

  <net id="ring" type="http://www.pnml.org/version-2009/grammar/ptnet">
    <page id="pg">
      <place id="p"><initialMarking><text>1</text></initialMarking></place>
      <transition id="t"/>
      <arc id="a" source="p" target="t"/>
    </page>
  </net>
</pnml>
"""


def test_a_deadlock_with_every_place_empty_points_at_the_net_element(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "ring.pnml"
    path.write_text(DEAD_RING)
    net, _ = load_for_analysis(str(path))
    findings = verdict_of(analyze(net, "interleaving", 100)).findings
    assert findings == (f"{path}:4: deadlock: marking {{}} reached by t; no transition can "
                        "ever fire there",)  # before: ring.pnml:0
    assert main(["check", str(path)]) == 0
    assert f"warning: {path}:4: deadlock" in capsys.readouterr().out


@pytest.mark.parametrize("name", sorted(p.name for p in (HERE / "pnml_tools").glob("*.pnml")))
def test_no_finding_of_the_other_tools_nets_is_at_line_0(name: str) -> None:
    net, _ = load_for_analysis(str(HERE / "pnml_tools" / name))
    for finding in verdict_of(analyze(net, "interleaving", 50)).findings:
        assert re.match(r"[^:]+:[1-9]\d*: ", finding), finding


def test_checks_verdict_says_its_budget_when_it_is_hit() -> None:
    verdict = verify(compile_file(ROOT / "programs" / "cell.yaml"), max_states=10)
    assert verdict.findings[-1].endswith(
        "cell.yaml:1: analysis incomplete: explored 10 states (check's budget; `softplc "
        f"analyze` explores up to {DEFAULT_MAX_STATES:,}); findings so far only")
