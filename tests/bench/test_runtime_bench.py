"""The runtime benchmark sections (scan, modbus, online_change, memory) run for real at tiny
durations: their output has the documented keys, numbers are numbers, something was counted,
the clients' replies were right, and every process they started is gone. Never timings."""

from __future__ import annotations

import json
import multiprocessing as mp
import numbers
from typing import Any

from softplc.bench import memorybench, modbusbench, onlinebench, scanbench
from softplc.bench.measure import Progress

QUIET = Progress(quiet=True)


def is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def no_children_left() -> bool:
    return all(not p.is_alive() for p in mp.active_children())


def test_scan_section_reports_floor_idle_and_loaded_with_histograms() -> None:
    result = scanbench.run(True, QUIET, duration_s=0.3, periods_ms=(1,))
    json.dumps(result)
    assert is_number(result["p99_ratio_loaded_over_floor_1ms"])
    assert isinstance(result["overruns_loaded_1ms"], int) and result["overruns_loaded_1ms"] >= 0
    for name in ("floor_1ms", "idle_1ms", "loaded_1ms"):
        config = result["configs"][name]
        assert config["scans"] > 0
        assert all(is_number(config["lateness_us"][k]) for k in ("p50", "p99", "p999", "max"))
        hist = result["histograms"][name]
        assert len(hist["edges_us"]) == len(hist["counts"]) + 1
        assert sum(hist["counts"]) == config["scans"]
    load = result["configs"]["loaded_1ms"]["load"]
    assert load["clients"] == 4 and load["requests"] > 0 and load["errors"] == 0
    assert load["http"]["requests"] > 0 and load["http"]["errors"] == 0
    assert no_children_left()


def test_modbus_section_compares_our_slave_with_plain_pymodbus() -> None:
    result = modbusbench.run(True, QUIET, duration_s=0.2, clients=(1, 4))
    json.dumps(result)
    assert is_number(result["throughput_ratio_vs_pymodbus_4c"])
    for name in ("ours_1c", "pymodbus_1c", "ours_4c", "pymodbus_4c"):
        run = result[name]
        assert run["requests"] > 0 and run["errors"] == 0, run["first_error"]
        assert is_number(run["requests_per_s"]) and is_number(run["latency_us"]["p99"])
    assert result["ours_4c"]["scan"]["scans"] > 0
    assert no_children_left()


def test_online_change_section_reaches_the_new_net_of_each_size() -> None:
    result = onlinebench.run(True, QUIET, sizes=(3, 5), repeats={3: 2, 5: 1})
    json.dumps(result)
    assert isinstance(result["missed_scans"], int) and result["missed_scans"] >= 0
    assert [c["transitions"] for c in result["changes"]] == [3, 3, 5]
    for change in result["changes"]:
        assert change["request_to_first_scan_ms"] > 0
        assert change["api"].startswith("online change to online_bench")
    assert is_number(result["by_size"]["5"]["split"]["compile_ms"])
    assert no_children_left()


def test_online_change_nets_carry_their_token_by_place_name() -> None:
    small, large = onlinebench.ring_program(3, 0), onlinebench.ring_program(5, 1)
    assert "p0: {tokens: 1}" in small and "spare1" in large and "spare1" not in small
    split = onlinebench.split_cost_ms(3, 5)  # raises if the online change were refused
    assert split["compile_ms"] > 0 and split["swap_and_scan_ms"] > 0


def test_memory_section_reports_rss_of_both_processes() -> None:
    result = memorybench.run(True, QUIET, duration_s=0.5, samples=2)
    json.dumps(result)
    assert result["rss_mb"] > 0
    assert result["start_mb"]["scan"] > 0 and result["end_mb"]["comm"] > 0
    assert result["modbus_requests"] > 0 and result["modbus_errors"] == 0
    assert result["plc_state_at_end"] == "RUNNING"
    assert no_children_left()
