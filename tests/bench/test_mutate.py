"""The mutation tester itself (softplc/bench/mutate.py, `make mutate`) on a tiny project: the
same seed draws the same mutants and writes the same text; a mutant the tiny test catches
is killed, one it cannot see survives, an endless loop times out; the project's own files
are never written."""

from __future__ import annotations

import os
import random
import signal
import subprocess
import threading
import time
from pathlib import Path

import pytest

from softplc.bench import mutate
from softplc.bench.mutants import every, mutated, sample
from softplc.bench.mutate import KILLED, SURVIVED, TIMEOUT, Settings, committed, markdown, run

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


def test_a_run_mutates_the_last_commit_not_an_edit_in_progress(tmp_path: Path) -> None:
    (tmp_path / "repo").mkdir()
    (tmp_path / "plain").mkdir()
    root = project(tmp_path / "repo")
    git = ["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "tiny"], check=True)
    (root / "tiny.py").write_text(TINY.replace("a + b", "a * b"))  # an edit in progress
    (root / "scratch.py").write_text("x = 1\n")  # and a file never committed
    with committed(root) as snapshot:
        assert snapshot != root
        assert (snapshot / "tiny.py").read_text() == TINY
        assert (snapshot / "tests" / "test_tiny.py").read_text() == TEST
        assert not (snapshot / "scratch.py").exists()
    assert not snapshot.exists()
    plain = project(tmp_path / "plain")  # not a checkout: the folder as it is
    with committed(plain) as same:
        assert same == plain


SLEEPS = '''import subprocess


def test_sleeps() -> None:
    subprocess.run(["sleep", "120"])
'''


def test_stop_kills_the_running_pytest_and_its_children(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    root = project(tmp_path)
    (root / "tests" / "test_sleeps.py").write_text(SLEEPS)
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")
    settings = Settings(hypothesis=False)
    result: list[tuple[int | None, float]] = []
    worker = threading.Thread(target=lambda: result.append(
        mutate._run(root, "tiny.py", TINY, ("tests/test_sleeps.py",), settings, 300.0)))
    worker.start()
    try:
        deadline = time.monotonic() + 60
        while not (mutate._LIVE and _sleeping(tmp_path)) and time.monotonic() < deadline:
            time.sleep(0.05)
        (group,) = mutate._LIVE
        assert _sleeping(tmp_path)  # pytest started its child
        with pytest.raises(SystemExit) as ended:
            mutate.stop(signal.SIGTERM)
        assert ended.value.code == 128 + signal.SIGTERM
        worker.join(30)
        assert not worker.is_alive() and not mutate._LIVE
        assert _running(group) == []  # the whole group: pytest and its sleep (zombies aside)
        assert not _sleeping(tmp_path)
    finally:
        mutate._STOPPING.clear()


def _running(group: int) -> list[int]:
    """The processes of process group `group` that are not zombies."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit():
                fields = (proc / "stat").read_text().rpartition(")")[2].split()
                if int(fields[2]) == group and fields[0] != "Z":
                    found.append(int(proc.name))
        except (OSError, ValueError, IndexError):
            continue
    return found


def _sleeping(root: Path) -> bool:
    """A `sleep 120` whose working directory is under `root` is running."""
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and (proc / "cmdline").read_bytes() == b"sleep\x00120\x00" \
                    and str(root) in os.readlink(proc / "cwd"):
                return True
        except OSError:
            continue
    return False
