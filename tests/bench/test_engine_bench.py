"""Engine-scaling benchmark: the generated nets, the three engines' agreement, the output's
structure. Never timings (the machine is shared and noisy)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.bench import engine
from softplc.bench.measure import Progress
from softplc.bench.netgen import FAMILIES, GenNet, chains, ring, to_compiled, to_yaml
from softplc.bench.refengine import RefEngine
from softplc.bench.snakes_net import SnakesEngine
from softplc.program.compiler import compile_text

ENGINE_NAMES = ("ours", "reference", "snakes", "snakes_incremental")


def _runners(net: GenNet) -> dict[str, engine.Runner]:
    return {name: factory(net) for name, factory in engine.ENGINES.items()}


@settings(max_examples=40, deadline=None)
@given(family=st.sampled_from(sorted(FAMILIES)), n=st.integers(1, 60), seed=st.integers(0, 9))
def test_all_engines_fire_the_same_steps(family: str, n: int, seed: int) -> None:
    net = FAMILIES[family](n, seed)
    runners = _runners(net)
    for _ in range(12):
        steps = {name: list(r.step()) for name, r in runners.items()}
        assert all(s == steps["ours"] for s in steps.values()), steps
    markings = {name: r.marking() for name, r in runners.items()}
    assert all(m == markings["ours"] for m in markings.values()), markings
    assert sum(markings["ours"]) == sum(net.initial)  # every family conserves tokens


def test_conflict_step_follows_priority_then_declaration_on_the_residual() -> None:
    net = FAMILIES["conflict"](10, 0)  # one hub, 3 tokens, ten competitors
    fired = RefEngine(net).step()
    order = list(net.order)
    assert fired == sorted(fired, key=order.index)
    assert sum(dict(net.transitions[i].pre)[0] for i in fired) == 3  # the hub is emptied
    assert list(SnakesEngine(net).step()) == fired
    assert list(engine.OursRunner(net).step()) == fired


def test_ring_fires_ten_transitions_every_round_at_every_size() -> None:
    for n in (10, 37, 1000):
        r = engine.OursRunner(ring(n))
        assert [len(r.step()) for _ in range(5)] == [10] * 5


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_direct_build_equals_the_compiled_program(family: str, tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text("symbols: {}\n", encoding="utf-8")
    net = FAMILIES[family](40, 3)
    compiled = compile_text(to_yaml(net, "io.yaml"), str(tmp_path / "net.yaml"))
    direct = to_compiled(net)
    assert direct.place_names == compiled.place_names
    assert direct.initial.tolist() == compiled.initial.tolist()
    unlined = [dataclasses.replace(t, line=0) for t in compiled.transitions]
    assert unlined == list(direct.transitions)
    assert direct.order == compiled.order
    assert direct.touching == compiled.touching
    assert direct.capacity.tolist() == compiled.capacity.tolist()


def test_a_different_step_is_an_error_not_a_figure() -> None:
    net = ring(10)  # ten tokens; chains(10) is the same cycle with one token
    runners = {"ours": engine.OursRunner(net), "other": RefEngine(chains(10))}
    with pytest.raises(engine.EngineMismatch, match="step of round 1"):
        engine._agree(net, runners, 3)


def test_snakes_is_skipped_above_its_limit_with_an_estimate() -> None:
    seen = {"snakes": (10_000, 2.0, 0.5)}
    skip = engine._snakes_skip("snakes", 100_000, engine.FULL, seen)
    assert skip is not None and skip.startswith("skipped: would take ~")
    assert engine._snakes_skip("ours", 100_000, engine.FULL, seen) is None
    assert engine._snakes_skip("snakes", 1_000, engine.FULL, seen) is None


def test_run_at_tiny_sizes_has_the_structure_and_keys() -> None:
    out = engine.run(quick=True, progress=Progress(quiet=True), sizes=[10, 100])
    json.dumps(out)  # serialisable
    for key in ("vs_snakes_1k", "scale_10k_over_10"):
        assert key in out and out[key] is None  # sizes 1,000 and 10,000 were not run
    assert out["all_agreed"] is True
    assert set(out["families"]) == set(FAMILIES)
    for family, data in out["families"].items():
        rows = data["rows"]
        assert {(r["n_transitions"], r["engine"]) for r in rows} == {
            (n, e) for n in (10, 100) for e in ENGINE_NAMES}
        for row in rows:
            assert row["family"] == family and "skipped" not in row
            assert row["rounds"] >= engine.QUICK.min_rounds
            assert set(row["round_us"]) >= {"median", "p99"}
            assert row["firings_per_s"] is None or row["firings_per_s"] >= 0
            assert row["memory_mb"] > 0
        for agreed in data["agreement"]:
            assert agreed["same_steps"] and agreed["same_marking"]
            assert agreed["engines"] == list(ENGINE_NAMES)
    assert set(out["vs_snakes"]["ring"]) == {"10", "100"}
    assert set(out["vs_reference"]["chains"]) == {"10", "100"}
