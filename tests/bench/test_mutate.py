"""The mutation tester itself (softplc/bench/mutate.py, `make mutate`) on a tiny project: the
same seed draws the same mutants and writes the same text; a mutant the tiny test catches
is killed, one it cannot see survives, an endless loop times out; the project's own files
are never written."""

from __future__ import annotations

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
