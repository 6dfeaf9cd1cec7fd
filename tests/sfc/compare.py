"""Run a chart two ways, scan by scan: the net it compiles to on the real scan (core), and the
reference interpreter (refsfc.py) on the XML; return the first scan where they disagree."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from softplc.program.compiler import compile_file
from tests.core.helpers import Bench
from tests.sfc.refsfc import RefSfc, read

PERIOD_MS = 10


def compare(path: Path, scans: list[dict[str, Any]]) -> str | None:
    net = compile_file(path)
    bench = Bench(net)  # its first scan (now 0) downloads and starts, all inputs 0
    ref = RefSfc(read(path.read_text(encoding="utf-8")))
    ref.scan(0, {})
    observed = [n for n, s in net.io.symbols.items() if not str(s.address).startswith("%I")
                and n in ref.c.types]  # the chart's variables (not the net's SD/SL latches)
    for k, values in enumerate(scans, start=1):
        bench.set(**{n: int(v) for n, v in values.items() if n in net.io.symbols})
        bench.scan(k * PERIOD_MS * 1_000_000)
        ref.scan(k * PERIOD_MS, values)
        net_steps = {p for p, n in bench.marking().items() if n and p in ref.c.steps}
        if net_steps != ref.active:
            return f"scan {k}: net steps {sorted(net_steps)} != reference {sorted(ref.active)}"
        for name in observed:
            got, want = bench.get(name), ref.env.get(name)
            if int(got) != int(want or 0):
                return f"scan {k}: {name} = {got} in the net, {want} in the reference"
    return None
