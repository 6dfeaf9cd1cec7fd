"""The `opcua` bench section runs end to end on a real runtime and reports every key.
Structure and sanity only, never timings (performance belongs in `make bench`)."""

from __future__ import annotations

from softplc.bench import opcuabench
from softplc.runtime.realtime import NORMAL


def test_opcua_section_reports_its_keys() -> None:
    seen: list[str] = []
    result = opcuabench.run(True, seen.append, duration_s=0.5, realtime=NORMAL)
    for key in ("reads_per_s", "notifications_per_s", "p99_ratio_over_floor_1ms",
                "call_to_effect_scans", "call_to_effect_scans_max", "overruns_1ms"):
        assert key in result, key
    assert result["reads_per_s"] > 0
    scans = result["call_to_effect"]["scans"]
    assert len(scans) == 3 and all(n >= 1 for n in scans)  # an effect needs at least a scan
    assert result["call_to_effect_scans_max"] == max(scans)
    assert any("call-to-effect" in line for line in seen)
