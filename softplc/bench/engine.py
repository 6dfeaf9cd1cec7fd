"""Engine scaling (issue 6, section 1): softplc's firing round against SNAKES and against a
plain-Python reference engine, on generated net families from 10 to 100,000 transitions.

Owns: per family and size, building each engine (memory: tracemalloc, what the build keeps),
checking that all engines fire the same steps and reach the same marking (a mismatch raises
EngineMismatch, before any time counts), then timing rounds; SNAKES is skipped where it would
take too long, with its extrapolated cost. Keys: `vs_snakes_1k` and `scale_10k_over_10`, both
on the ring family, where exactly 10 transitions fire in every round at every size.
Does not know: how nets are generated (netgen), SNAKES' API (snakes_net), the CLI, plots.
"""

from __future__ import annotations

import gc
import time
import tracemalloc
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, Protocol

from softplc.bench.measure import Progress, figures, ratio
from softplc.bench.netgen import FAMILIES, GenNet, to_compiled
from softplc.bench.refengine import RefEngine
from softplc.bench.snakes_net import SnakesEngine
from softplc.core.engine import Engine
from softplc.core.errors import SoftplcError
from softplc.core.expr import NoValues

SIZES = (10, 100, 1_000, 10_000, 100_000)
QUICK_SIZES = (10, 100, 1_000, 10_000)
KEY_FAMILY = "ring"
SEED = 0
OURS, REFERENCE = "ours", "reference"
SNAKES, SNAKES_INCREMENTAL = "snakes", "snakes_incremental"


class EngineMismatch(SoftplcError):
    """Two engines fired different steps or reached different markings: a bug, not a figure."""


class Runner(Protocol):
    def step(self) -> Sequence[int]: ...  # fired transition indices, in step order

    def marking(self) -> list[int]: ...


class OursRunner:
    """softplc's Engine as a scan calls it: one `fire_round` per scan, time advancing."""

    def __init__(self, net: GenNet) -> None:
        self.engine = Engine(to_compiled(net))
        self.ctx = NoValues()
        self.now_ns = 0

    def step(self) -> Sequence[int]:
        self.now_ns += 1_000_000
        return self.engine.fire_round(self.ctx, self.now_ns).fired

    def marking(self) -> list[int]:
        return [int(k) for k in self.engine.state.marking.tolist()]


ENGINES: dict[str, Callable[[GenNet], Runner]] = {
    OURS: OursRunner,
    REFERENCE: RefEngine,
    SNAKES: SnakesEngine,
    SNAKES_INCREMENTAL: partial(SnakesEngine, incremental=True),
}


@dataclass(frozen=True, slots=True)
class Budget:
    check_rounds: int  # rounds every engine runs in lockstep before any timing
    min_rounds: int
    max_rounds: int
    seconds: Mapping[str, float]  # timing budget per engine and cell
    snakes_max_n: int  # SNAKES is not built above this size
    snakes_cap_s: float  # nor where its build, check and minimal timing would take longer


# Quick mode runs SNAKES up to 1,000 transitions only (where the key is): its 10,000-transition
# nets alone take ~10 s to build on a 2-core machine.
QUICK = Budget(4, 3, 2_000, {OURS: 0.1, REFERENCE: 0.08, SNAKES: 0.15, SNAKES_INCREMENTAL: 0.1},
               1_000, 4.0)
FULL = Budget(20, 5, 20_000, {OURS: 1.0, REFERENCE: 0.5, SNAKES: 1.5, SNAKES_INCREMENTAL: 1.0},
              10_000, 30.0)


# engine -> (n, build s, median round s) of the largest size SNAKES ran at in a family: the
# base of the cost extrapolation.
_Seen = dict[str, tuple[int, float, float]]


def run(quick: bool, progress: Progress, sizes: Sequence[int] | None = None) -> dict[str, Any]:
    budget = QUICK if quick else FULL
    sizes = tuple(sizes) if sizes is not None else (QUICK_SIZES if quick else SIZES)
    families: dict[str, Any] = {}
    for family in FAMILIES:
        seen: _Seen = {}
        rows: list[dict[str, Any]] = []
        agreement: list[dict[str, Any]] = []
        for n in sizes:
            cell_rows, agreed = _cell(family, n, budget, progress, seen)
            rows += cell_rows
            agreement.append(agreed)
        families[family] = {"description": _describe(family), "rows": rows,
                            "agreement": agreement}
    progress.done()
    return _summary(families, quick, sizes, budget)


def _describe(family: str) -> str:
    doc = FAMILIES[family].__doc__ or ""
    return " ".join(doc.split())


def _cell(family: str, n: int, budget: Budget, progress: Progress,
          seen: _Seen) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    net = FAMILIES[family](n, SEED)
    label = f"{family} {len(net.transitions)} transitions"
    runners: dict[str, Runner] = {}
    rows: list[dict[str, Any]] = []
    built: dict[str, tuple[float, float]] = {}
    for engine, factory in ENGINES.items():
        skip = _snakes_skip(engine, n, budget, seen)
        if skip is not None:
            rows.append({**_ident(net, engine), "skipped": skip})
            continue
        progress(f"engine: {label} ({engine}, build)")
        runners[engine], built[engine] = _build(factory, net)
    progress(f"engine: {label} (all engines, {budget.check_rounds} rounds in lockstep)")
    agreed = _agree(net, runners, budget.check_rounds)
    for engine, runner in runners.items():
        progress(f"engine: {label} ({engine}, timing)")
        samples, fired = _time(runner, budget.seconds[engine], budget.min_rounds,
                               budget.max_rounds)
        row = _row(net, engine, samples, fired, *built[engine])
        rows.append(row)
        if engine.startswith(SNAKES):
            seen[engine] = (n, built[engine][1], row["round_us"]["median"] / 1e6)
    return rows, agreed


def _snakes_skip(engine: str, n: int, budget: Budget, seen: _Seen) -> str | None:
    """Why SNAKES is not run at this size (with its extrapolated cost), or None to run it."""
    if not engine.startswith(SNAKES):
        return None
    base = seen.get(engine)
    estimate = None
    if base is not None:
        base_n, build_s, round_s = base
        rounds = budget.check_rounds + budget.min_rounds
        # Build and SNAKES' enabling both grow linearly with the net (measured at 1k-10k).
        estimate = (build_s + rounds * round_s) * n / base_n
    if n <= budget.snakes_max_n and (estimate is None or estimate <= budget.snakes_cap_s):
        return None
    where = f"extrapolated linearly from {base[0]} transitions" if base else "no smaller run"
    cost = f"~{estimate:.0f} s" if estimate is not None else "too long"
    return (f"skipped: would take {cost} ({where}); limits {budget.snakes_max_n} transitions, "
            f"{budget.snakes_cap_s:.0f} s")


def _build(factory: Callable[[GenNet], Runner], net: GenNet) -> tuple[Runner, tuple[float, float]]:
    """The engine, and (MB it keeps allocated, build seconds under tracemalloc)."""
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        began = time.perf_counter()
        runner = factory(net)
        build_s = time.perf_counter() - began
        kept = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    return runner, (kept / 1e6, build_s)


def _agree(net: GenNet, runners: Mapping[str, Runner], rounds: int) -> dict[str, Any]:
    """Run every engine `rounds` rounds in lockstep; raise EngineMismatch at the first
    difference in a step or in the marking."""
    names = list(runners)
    for k in range(rounds):
        steps = {name: list(runners[name].step()) for name in names}
        _same(net, f"step of round {k + 1}", steps)
    markings = {name: runners[name].marking() for name in names}
    _same(net, f"marking after {rounds} rounds", markings)
    return {"n_transitions": len(net.transitions), "rounds": rounds, "engines": names,
            "same_steps": True, "same_marking": True,
            "tokens": sum(markings[names[0]]) if names else 0}


def _same(net: GenNet, what: str, values: Mapping[str, list[int]]) -> None:
    first, *others = values
    for other in others:
        if values[other] != values[first]:
            raise EngineMismatch(f"{net.name}: {what} differs between {first} and {other}: "
                                 f"{_brief(values[first])} vs {_brief(values[other])}")


def _brief(xs: list[int]) -> str:
    return repr(xs[:20]) + (f" ... ({len(xs)} items)" if len(xs) > 20 else "")


def _time(runner: Runner, seconds: float, min_rounds: int,
          max_rounds: int) -> tuple[list[float], int]:
    """Microseconds of each timed round, and the firings in them."""
    clock = time.perf_counter_ns
    samples: list[float] = []
    fired = 0
    gc.collect()
    deadline = clock() + int(seconds * 1e9)
    while len(samples) < max_rounds and (len(samples) < min_rounds or clock() < deadline):
        began = clock()
        fired += len(runner.step())
        samples.append((clock() - began) / 1e3)
    return samples, fired


def _ident(net: GenNet, engine: str) -> dict[str, Any]:
    return {"family": net.family, "name": net.name, "n_transitions": len(net.transitions),
            "n_places": len(net.places), "engine": engine}


def _row(net: GenNet, engine: str, samples: list[float], fired: int, memory_mb: float,
         build_s: float) -> dict[str, Any]:
    total_s = sum(samples) / 1e6
    return {**_ident(net, engine), "rounds": len(samples),
            "round_us": figures(samples).as_dict(),
            "firings_per_round": fired / len(samples),
            "firings_per_s": fired / total_s if total_s > 0 else None,
            "memory_mb": memory_mb, "build_s": build_s}


# -- summary ---------------------------------------------------------------------------------

def _medians(families: Mapping[str, Any]) -> dict[tuple[str, int, str], float]:
    return {(f, r["n_transitions"], r["engine"]): r["round_us"]["median"]
            for f, data in families.items() for r in data["rows"] if "round_us" in r}


def _ratios(med: Mapping[tuple[str, int, str], float], num: str, den: str
            ) -> dict[str, dict[str, float | None]]:
    """family -> size -> median round time of `num` / that of `den` (where both ran)."""
    out: dict[str, dict[str, float | None]] = {}
    for (family, n, engine), value in sorted(med.items()):
        if engine == num and (family, n, den) in med:
            out.setdefault(family, {})[str(n)] = ratio(value, med[(family, n, den)])
    return out


def _summary(families: dict[str, Any], quick: bool, sizes: Sequence[int],
             budget: Budget) -> dict[str, Any]:
    med = _medians(families)

    def key_ratio(num: tuple[str, int, str], den: tuple[str, int, str]) -> float | None:
        return ratio(med[num], med[den]) if num in med and den in med else None

    ring = KEY_FAMILY
    return {
        "vs_snakes_1k": key_ratio((ring, 1_000, SNAKES), (ring, 1_000, OURS)),
        "vs_snakes_incremental_1k": key_ratio((ring, 1_000, SNAKES_INCREMENTAL),
                                              (ring, 1_000, OURS)),
        "scale_10k_over_10": key_ratio((ring, 10_000, OURS), (ring, 10, OURS)),
        "key_family": ring,
        "key_note": ("ring: one cycle with 10 tokens, so 10 transitions fire in every round at "
                     "every size; ratios of median round times"),
        "targets": {"vs_snakes_1k": ">= 100", "scale_10k_over_10": "<= 3"},
        "quick": quick,
        "sizes": list(sizes),
        "budget": {"check_rounds": budget.check_rounds, "min_rounds": budget.min_rounds,
                   "seconds": dict(budget.seconds), "snakes_max_n": budget.snakes_max_n,
                   "snakes_cap_s": budget.snakes_cap_s},
        "vs_snakes": _ratios(med, SNAKES, OURS),
        "vs_snakes_incremental": _ratios(med, SNAKES_INCREMENTAL, OURS),
        "vs_reference": _ratios(med, REFERENCE, OURS),
        "all_agreed": all(a["same_steps"] and a["same_marking"]
                          for data in families.values() for a in data["agreement"]),
        "families": families,
    }
