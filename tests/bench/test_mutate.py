"""The mutation tester itself (softplc/bench/mutate.py, `make mutate`) on a tiny project: the
same seed draws the same mutants and writes the same text; a mutant the tiny test catches
is killed, one it cannot see survives, an endless loop times out; the project's own files
are never written."""

from __future__ import annotations

import random
from pathlib import Path

import pytest

from softplc.bench.mutants import every, mutated, sample
from softplc.bench.mutate import KILLED, SURVIVED, TIMEOUT, Settings, markdown, run

TINY = '''def add(a: int, b: int) -> int:
    return a + b


def limit() -> int:
    return 3
'''
LOOP = '''def spin(n: int, step: int) -> int:
    while n:
        n -= step
    return n
'''
TEST = '''from loop import spin
from tiny import add


def test_add() -> None:
    assert add(2, 3) == 5


def test_spin() -> None:
    assert spin(3, 1) == 0
'''


def project(root: Path) -> Path:
    (root / "pytest.ini").write_text("[pytest]\n")
    (root / "tiny.py").write_text(TINY)
    (root / "loop.py").write_text(LOOP)
    (root / "tests").mkdir()
    (root / "tests" / "test_tiny.py").write_text(TEST)
    return root


def test_the_same_seed_draws_the_same_mutants_and_text() -> None:
    first, sites = sample("tiny.py", TINY, 3, seed=7)
    again, _ = sample("tiny.py", TINY, 3, seed=7)
    assert first == again and len(first) == 3 and sites == 5
    assert [mutated(TINY, m) for m in first] == [mutated(TINY, m) for m in again]
    assert [m.description for m in every("tiny.py", TINY)] == [
        "return None: `return a + b` -> `return None`",
        "arithmetic: `a + b` -> `a - b`",
        "return None: `return 3` -> `return None`",
        "constant +1: `3` -> `4`",
        "constant -1: `3` -> `2`",
    ]
    assert "return a - b" in mutated(TINY, every("tiny.py", TINY)[1])


def test_caught_mutants_are_killed_unseen_ones_survive_and_endless_ones_time_out(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = project(tmp_path)
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")  # 0.2 s a run, not 1.6 s
    settings = Settings(seed=1, size=10, jobs=2, budget_s=120.0, timeout_factor=2.0,
                        timeout_floor_s=4.0, hypothesis=False)
    tiny, loop = run(root, {"tiny.py": ("tests",), "loop.py": ("tests",)}, settings,
                     quiet=True)
    assert (root / "tiny.py").read_text() == TINY and (root / "loop.py").read_text() == LOOP
    assert [m.line for m in tiny.outcomes[KILLED]] == [2, 2]  # add's two
    assert [m.line for m in tiny.outcomes[SURVIVED]] == [6, 6, 6]  # limit's three
    assert {m.description for m in loop.outcomes[TIMEOUT]} == {
        "delete statement: `n -= step` -> `pass`", "arithmetic: `n -= step` -> `n += step`"}
    assert len(loop.outcomes[KILLED]) == 3 and SURVIVED not in loop.outcomes
    table = markdown([tiny, loop], {tiny.outcomes[SURVIVED][0].key: "never called"}, "tiny")
    assert "| tiny.py | 5 | 5 | 2 | 3 | 0 | 1 | 0 | 50.0 % |" in table
    assert "| loop.py | 5 | 5 | 3 | 0 | 2 | 0 | 0 | 100.0 % |" in table


MANY = '''def table() -> list[int]:
    return [10, 20, 30, 40, 50, 60]
'''
SEEN = '''import os
import random
from pathlib import Path


def test_record() -> None:
    with open(os.environ["MUTATE_SEEN"], "a", encoding="utf-8") as log:
        log.write(Path(__file__).parent.parent.joinpath("many.py").read_text() + "\\0")
'''


def test_a_run_takes_its_mutants_in_the_order_of_the_seeded_draw(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run the budget cuts after k mutants must have run a fair random k, not the top of
    the module: the mutants run in the order they were drawn, not in source order."""
    found = every("many.py", MANY)
    drawn, sites = sample("many.py", MANY, 6, seed=5)
    order = random.Random("5:many.py").sample(range(sites), 6)
    assert [m.index for m in drawn] == order != sorted(order)
    assert all(found[m.index] == m for m in drawn)
    root = tmp_path / "project"
    root.mkdir()
    (root / "pytest.ini").write_text("[pytest]\n")
    (root / "many.py").write_text(MANY)
    (root / "tests").mkdir()
    (root / "tests" / "test_seen.py").write_text(SEEN)
    log = tmp_path / "seen"
    monkeypatch.setenv("MUTATE_SEEN", str(log))
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")
    settings = Settings(seed=5, size=6, jobs=1, budget_s=120.0, hypothesis=False)
    (many,) = run(root, {"many.py": ("tests",)}, settings, quiet=True)
    assert len(many.outcomes[SURVIVED]) == 6  # the test looks at nothing: all survive
    ran = log.read_text().split("\0")[:-1]
    assert ran[1:] == [mutated(MANY, m) for m in drawn]  # after the baseline, as drawn
