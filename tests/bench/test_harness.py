"""The harness end to end at tiny sizes: real engine and scan sections, a failing section that
must not lose the others, then JSON, plots and BENCHMARKS.md. Structure only, never timings."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from softplc.bench import engine, harness, scanbench
from softplc.bench.measure import Progress
from softplc.bench.report import headline_table, write_markdown, write_plots


def tiny(name: str) -> Callable[[bool, Progress], dict[str, Any]]:
    if name == "engine":
        return lambda quick, progress: engine.run(quick, progress, sizes=[10, 100])
    if name == "scan":
        return lambda quick, progress: scanbench.run(quick, progress, duration_s=0.3,
                                                     periods_ms=(1,))

    def broken(quick: bool, progress: Progress) -> dict[str, Any]:
        raise RuntimeError("this section is broken on purpose")

    return broken


def test_harness_writes_every_headline_key_plots_and_markdown(tmp_path: Path) -> None:
    results = harness.run_sections(["engine", "scan", "modbus"], True, Progress(quiet=True),
                                   runner=tiny)
    assert set(results["headline"]) == set(harness.HEADLINE)
    assert results["headline"]["scan.p99_ratio_loaded_over_floor_1ms"] is not None
    assert isinstance(results["headline"]["scan.overruns_loaded_1ms"], int)
    assert results["headline"]["engine.scale_10k_over_10"] is None  # 10,000 was not run
    assert "RuntimeError: this section is broken on purpose" in \
        results["sections"]["modbus"]["error"]
    assert results["headline"]["modbus.throughput_ratio_vs_pymodbus_4c"] is None
    assert {t["met"] for t in results["targets"]} <= {True, False, None}
    json.loads(json.dumps(results, default=str))

    plots = write_plots(results, tmp_path / "plots")
    assert {Path(p).name for p in plots} == {"engine_scaling.png", "lateness_1ms.png"}
    assert all(Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots)
    results["plots"] = plots
    write_markdown(results, tmp_path / "BENCHMARKS.md")
    text = (tmp_path / "BENCHMARKS.md").read_text()
    for key in harness.HEADLINE:
        assert f"| {key} |" in text
    assert "**This section failed:**" in text and "lateness_1ms.png" in text
    assert results["machine"]["cpu"] in text
    assert "scan.overruns_loaded_1ms" in headline_table(results)


def test_unknown_section_is_refused_with_the_list_of_known_ones(capsys: Any) -> None:
    args = argparse.Namespace(quick=True, json_file=None, plots=None, markdown=None,
                              only="engine,warp", quiet=True)
    assert harness.main(args) == 2
    assert "unknown section(s) warp" in capsys.readouterr().err


def test_the_summary_explains_itself() -> None:
    """Units, period, meaning, verdict and the pointer to BENCHMARKS.md, from a result dict."""
    values = {"engine.vs_snakes_1k": 320.0, "engine.scale_10k_over_10": None,
              "scan.p99_ratio_loaded_over_floor_1ms": 1.5, "scan.overruns_loaded_1ms": 3,
              "modbus.throughput_ratio_vs_pymodbus_4c": 1.2, "online_change.missed_scans": 0,
              "memory.rss_mb": 90.0}
    results: dict[str, Any] = {
        "mode": "quick", "machine": {"cpu": "Test CPU", "cores": 2, "load_average": [0.5]},
        "seconds": {"engine": 10.0, "scan": 20.0}, "headline": values,
        "sections": {"memory": {"period_ms": 10}},
        "targets": [{"key": t.key, "target": f"{t.op} {t.bound:g}", "meaning": t.meaning,
                     "unit": t.unit, "period": t.period, "value": values.get(t.key),
                     "met": t.met(values.get(t.key))} for t in harness.TARGETS],
    }
    text = harness_summary(results)
    assert "softplc bench (quick): 2 section(s) in 30 s on Test CPU (2 cores" in text
    lines = {line.split()[0]: line for line in text.splitlines() if line.strip()}
    assert lines["engine.vs_snakes_1k"].split()[1:5] == ["320x", ">=", "300x", "met"]
    assert "SNAKES round time / ours" in lines["engine.vs_snakes_1k"]
    assert lines["scan.overruns_loaded_1ms"].split()[1:7] == ["3", "scans", "==", "0", "MISSED",
                                                              "1"]
    assert lines["engine.scale_10k_over_10"].split()[1:5] == ["—", "<=", "3x", "not"]
    assert lines["memory.rss_mb"].split()[1:6] == ["90", "MB", "-", "reported", "10"]
    unmeasured = len(harness.TARGETS) - 5  # the targets this test gives no value
    assert "verdict: 4 of 5 measured target(s) met; missed: scan.overruns_loaded_1ms; " \
           f"not measured: {unmeasured}" in text
    assert "BENCHMARKS.md" in text and "period = the PLC scan period" in text


def harness_summary(results: dict[str, Any]) -> str:
    from softplc.bench.report import summary

    return summary(results)
