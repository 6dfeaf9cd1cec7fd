"""The `web` benchmark section runs end to end in a short form and reports its keys."""

from __future__ import annotations

from softplc.bench import webbench
from softplc.bench.harness import SECTIONS, TARGETS
from softplc.runtime.realtime import Realtime


def test_the_web_section_reports_its_keys() -> None:
    result = webbench.run(True, lambda message: None, duration_s=0.6, periods_ms=(10,),
                          realtime=Realtime())
    run = result["pages_10ms"]
    assert run["pages"]["pages"] == webbench.PAGES and run["scans"] > 0
    assert 0 < result["frames_per_s_per_page_10ms"] <= 30  # decimated to the page's rate
    assert result["bytes_per_s_per_page_10ms"] > 0
    assert "web" in SECTIONS and any(t.key == "web.p99_ratio_over_floor_1ms" for t in TARGETS)
