"""The third case study: the drilling cell drawn as an SFC (programs/drilling_sfc.xml, as a
Beremiz user writes it) drills as many parts per hour on the simulated plant as the YAML net
(programs/drilling.yaml): two real `softplc simulate` processes, same plant, same seed."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parents[2]


def drilled(program: str) -> int:
    run = subprocess.run([sys.executable, "-m", "softplc.cli", "simulate", program,
                          "--duration", "10min", "--json"], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return int(json.loads(run.stdout)["outputs_final"]["parts_drilled"])


def test_the_sfc_drilling_cell_drills_as_many_parts_as_the_yaml_net() -> None:
    sfc, net = drilled("programs/drilling_sfc.xml"), drilled("programs/drilling.yaml")
    assert sfc == net > 40  # 43 in 10 min: 257 an hour each (1h runs, docs/sfc.md)
