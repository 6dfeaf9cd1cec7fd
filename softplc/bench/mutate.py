"""`make mutate` (issue 43): the modules where a bug hurts most, each against its own fast
tests, one seeded sample of mutants per module.

Owns: the map of module -> fast tests (no socket, no process, seconds each), the private
copies of the last commit (one per worker: the working tree is never written nor measured,
others edit and run tests in it meanwhile), pytest per mutant with a timeout inside a
whole-run budget, its process group killed on SIGTERM/SIGINT, the report (JSON and Markdown)
and the known-equivalent mutants read from a file.
Does not know: how a mutant is made (mutants.py), what the modules do.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from softplc.bench.mutants import Mutant, mutated, sample, unmutated

LIFECYCLE = ("tests/core/test_lifecycle.py", "tests/core/test_scan.py",
             "tests/core/test_startup.py", "tests/core/test_faults.py", "tests/test_contracts.py")
ENGINE = ("tests/core/test_steps.py", "tests/core/test_limits.py",
          "tests/core/test_firing.py", "tests/core/test_engine_oracle.py")
SIGNED = ("tests/security/test_programgate.py", "tests/security/test_rollback.py",
          *(f"tests/security/test_signing.py::test_{name}" for name in (
              "trusted_keys_refuse_unsigned_untrusted_and_changed_downloads",
              "a_key_pair_is_private_and_never_overwritten",
              "only_a_trusted_key_over_the_exact_bytes_verifies",
              "signing_helpers_version_limit_is_eighteen_digits",
              "signing_helpers_trust_at_most_256_keys", "signing_helpers_key_names_and_files",
              "signing_helpers_refuse_unusable_key_files")))
# Each module's own fast tests: in-process, no socket, no child process (the softplc-run
# tests of test_retain.py and test_limits_download.py are left out by -k).
TARGETS: dict[str, tuple[str, ...]] = {
    "softplc/core/lifecycle.py": LIFECYCLE,
    **{f"softplc/core/engine/{name}.py": ENGINE for name in (
        "bindings", "capacity", "counts", "diagnostics", "enabling", "engine", "live",
        "outputs", "produce", "selection", "tables")},
    "softplc/core/expr.py": ("tests/core/test_expr.py", "tests/core/test_types.py",
                             "tests/program/test_wire.py"),
    "softplc/hmi/frames.py": ("tests/hmi/test_frames.py",),
    "softplc/hmi/map.py": ("tests/hmi/test_map.py", "tests/hmi/test_frames.py",
                           "tests/hmi/test_eng_registers.py", "tests/hmi/test_long_registers.py",
                           "tests/hmi/test_nonfinite_modbus.py", "tests/test_contracts.py"),
    "softplc/runtime/retain/codec.py": ("tests/runtime/test_typed_hold.py",
                                        "tests/runtime/test_retain_store.py",
                                        "tests/runtime/test_retain_per_variable.py",
                                        "tests/runtime/test_retain.py", "-k", "not softplc_run"),
    "softplc/program/bundle.py": ("tests/program/test_limits_download.py", "-k", "bundle"),
    "softplc/security/signing.py": SIGNED,
    "softplc/security/decide.py": ("tests/security/test_decide.py",),
    "softplc/security/programgate.py": SIGNED[:2],
    "softplc/security/roles.py": ("tests/security/test_decide.py", "tests/security/test_doors.py"),
}
# What a copy of the tree leaves out (the .gitignore's caches, the venv, a run's state).
IGNORED = (".git", ".venv", "__pycache__", ".hypothesis", ".mypy_cache", ".ruff_cache",
           ".pytest_cache", "*.egg-info", "build", "state", "*.trace.jsonl")
KILLED, SURVIVED, TIMEOUT, NOT_RUN = "killed", "survived", "timed out", "not run"
_LIVE: set[int] = set()  # process groups of the pytest runs going on
_STOPPING = threading.Event()


@dataclass(frozen=True, slots=True)
class Settings:
    seed: int = 43
    size: int = 20  # mutants per module
    jobs: int = 2
    budget_s: float = 840.0  # no mutant starts after this; baselines and copies count
    timeout_factor: float = 3.0  # a mutant's timeout: this x its module's baseline + floor
    timeout_floor_s: float = 10.0
    hypothesis: bool = True  # the tests draw their examples from `seed`
    python: str = sys.executable


@dataclass(slots=True)
class Module:
    path: str
    tests: tuple[str, ...]
    sites: int = 0
    baseline_s: float | None = None  # None: the tests failed on the unmutated module
    outcomes: dict[str, list[Mutant]] = field(default_factory=dict)

    def count(self, status: str) -> int:
        return len(self.outcomes.get(status, []))


def _pytest(settings: Settings, tests: Sequence[str]) -> list[str]:
    seeded = [f"--hypothesis-seed={settings.seed}"] if settings.hypothesis else []
    return [settings.python, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *seeded,
            *tests]


@contextmanager
def committed(root: Path) -> Iterator[Path]:
    """The last commit of `root` as files in a temporary folder (a run measures what is
    committed, never an edit in progress); `root` itself when it is not a git checkout."""
    if not (root / ".git").exists():
        yield root
        return
    snapshot = Path(tempfile.mkdtemp(prefix="softplc-mutate-head-"))
    try:
        archive = subprocess.run(["git", "-C", str(root), "archive", "--format=tar", "HEAD"],
                                 check=True, capture_output=True).stdout
        with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
            tar.extractall(snapshot, filter="data")
        yield snapshot
    finally:
        shutil.rmtree(snapshot, ignore_errors=True)


def stop(signum: int, _frame: object = None) -> None:
    """SIGTERM or SIGINT: every pytest run going on is killed with its children (each has its
    own process group), no new one starts, and the run ends (its copies removed)."""
    _STOPPING.set()
    for group in list(_LIVE):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(group, signal.SIGKILL)
    raise SystemExit(128 + signum)


def _copy(root: Path, settings: Settings) -> Path:
    tree = Path(tempfile.mkdtemp(prefix="softplc-mutate-")) / "tree"
    shutil.copytree(root, tree, symlinks=True, ignore=shutil.ignore_patterns(*IGNORED))
    subprocess.run([settings.python, "-m", "compileall", "-q", "."], cwd=tree,
                   stdout=subprocess.DEVNULL, check=False)  # once, not per pytest
    return tree


def _run(tree: Path, path: str, text: str, tests: Sequence[str], settings: Settings,
         timeout_s: float) -> tuple[int | None, float]:
    """Pytest's exit status with `text` as the module in `tree` (None: timed out), and the
    seconds it took; the module is put back after."""
    target = tree / path
    original = target.read_bytes()
    compiled = Path(importlib.util.cache_from_source(str(target)))
    env = {**os.environ, "PYTHONHASHSEED": "0",
           "PYTHONPATH": os.pathsep.join([str(tree), *filter(None, [os.environ.get(
               "PYTHONPATH")])])}
    try:
        target.write_text(text, encoding="utf-8")
        compiled.unlink(missing_ok=True)  # a stale .pyc of the same size and second
        shutil.rmtree(tree / ".hypothesis", ignore_errors=True)  # no example from a mutant
        start = time.monotonic()
        proc = subprocess.Popen(_pytest(settings, tests), cwd=tree, env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        _LIVE.add(proc.pid)
        try:
            if _STOPPING.is_set():  # stop() came between the start and the line above
                raise subprocess.TimeoutExpired(proc.args, 0)
            status: int | None = proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # its own group: pytest and its children
            proc.wait()
            status = None
        finally:
            _LIVE.discard(proc.pid)
        return status, time.monotonic() - start
    finally:
        target.write_bytes(original)
        compiled.unlink(missing_ok=True)


@contextmanager
def _copies(root: Path, settings: Settings) -> Iterator[queue.Queue[Path]]:
    trees: queue.Queue[Path] = queue.Queue()
    made = []
    try:
        with ThreadPoolExecutor(settings.jobs) as pool:
            made = list(pool.map(lambda _: _copy(root, settings), range(settings.jobs)))
        for tree in made:
            trees.put(tree)
        yield trees
    finally:
        for tree in made:
            shutil.rmtree(tree.parent, ignore_errors=True)


def run(root: Path, targets: Mapping[str, Sequence[str]], settings: Settings,
        quiet: bool = False) -> list[Module]:
    """Every target's baseline, then its sampled mutants, in copies of `root`."""
    deadline = time.monotonic() + settings.budget_s
    modules = [Module(path, tuple(tests)) for path, tests in targets.items()]
    sources = {m.path: (root / m.path).read_text(encoding="utf-8") for m in modules}
    drawn = {}
    for module in modules:
        drawn[module.path], module.sites = sample(module.path, sources[module.path],
                                                  settings.size, settings.seed)
    with _copies(root, settings) as trees, ThreadPoolExecutor(settings.jobs) as pool:
        def baseline(module: Module) -> None:
            tree = trees.get()
            try:
                status, seconds = _run(tree, module.path, unmutated(sources[module.path],
                                       module.path), module.tests, settings, 600.0)
            finally:
                trees.put(tree)
            module.baseline_s = seconds if status == 0 else None

        def one(module: Module, mutant: Mutant) -> None:
            status: int | None = 0
            if module.baseline_s is None or time.monotonic() > deadline or _STOPPING.is_set():
                verdict = NOT_RUN
            else:
                tree = trees.get()
                try:
                    status, _ = _run(tree, module.path, mutated(sources[module.path], mutant),
                                     module.tests, settings,
                                     settings.timeout_factor * module.baseline_s
                                     + settings.timeout_floor_s)
                finally:
                    trees.put(tree)
                verdict = TIMEOUT if status is None else SURVIVED if status == 0 else KILLED
            module.outcomes.setdefault(verdict, []).append(mutant)
            if verdict in (SURVIVED, TIMEOUT) and not quiet:
                print(f"{verdict}: {mutant.path}:{mutant.line} {mutant.description}",
                      file=sys.stderr, flush=True)

        list(pool.map(baseline, modules))
        # round-robin over the modules, each module's mutants in the order of their seeded
        # draw: a budget cut shortens every module's sample alike and leaves it random
        order = sorted(((rank, n, module, mutant) for n, module in enumerate(modules)
                        for rank, mutant in enumerate(drawn[module.path])),
                       key=lambda job: (job[0], job[1]))
        list(pool.map(lambda job: one(job[2], job[3]), order))
    for module in modules:
        for mutants in module.outcomes.values():
            mutants.sort(key=lambda m: m.index)
    return modules


def load_equivalent(path: Path | None) -> dict[str, str]:
    """key -> why it is equivalent, from lines `KEY | reason` (# starts a comment line)."""
    if path is None or not path.exists():
        return {}
    found = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, why = line.partition(" | ")
            found[key.strip()] = why.strip()
    return found


def score(m: Module, equivalent: Mapping[str, str]) -> tuple[int, float | None]:
    """The module's equivalent survivors, and killed / (killed + survived - equivalent)
    in per cent (timeouts apart, neither killed nor survived)."""
    same = sum(s.key in equivalent for s in m.outcomes.get(SURVIVED, []))
    real = m.count(KILLED) + m.count(SURVIVED) - same
    return same, round(100.0 * m.count(KILLED) / real, 1) if real else None


def summary(m: Module, equivalent: Mapping[str, str]) -> dict[str, object]:
    same, percent = score(m, equivalent)
    return {
        "module": m.path, "tests": list(m.tests), "sites": m.sites,
        "baseline_s": None if m.baseline_s is None else round(m.baseline_s, 1),
        "tried": m.count(KILLED) + m.count(SURVIVED) + m.count(TIMEOUT),
        "killed": m.count(KILLED), "survived": m.count(SURVIVED), "timed_out": m.count(TIMEOUT),
        "equivalent": same, "not_run": m.count(NOT_RUN), "score": percent,
        "survivors": [{"file": s.path, "line": s.line, "mutation": s.description,
                       "key": s.key, "equivalent": equivalent.get(s.key)}
                      for s in m.outcomes.get(SURVIVED, [])],
        "timeouts": [{"file": s.path, "line": s.line, "mutation": s.description}
                     for s in m.outcomes.get(TIMEOUT, [])],
    }


def markdown(modules: Sequence[Module], equivalent: Mapping[str, str], header: str) -> str:
    lines = [header, "", "| module | sites | tried | killed | survived | timed out | "
             "equivalent | not run | score |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for m in modules:
        same, percent = score(m, equivalent)
        shown = "baseline failed" if m.baseline_s is None else \
            "-" if percent is None else f"{percent} %"
        tried = m.count(KILLED) + m.count(SURVIVED) + m.count(TIMEOUT)
        lines.append(f"| {m.path.removeprefix('softplc/')} | {m.sites} | {tried} | "
                     f"{m.count(KILLED)} | {m.count(SURVIVED)} | {m.count(TIMEOUT)} | {same} | "
                     f"{m.count(NOT_RUN)} | {shown} |")
    for title, status in (("Survivors", SURVIVED), ("Timed out", TIMEOUT)):
        found = [s for m in modules for s in m.outcomes.get(status, [])]
        lines += ["", f"{title}:", "", *(
            f"- `{s.path}:{s.line}` {s.description}" + (
                f" (equivalent: {equivalent[s.key]})" if s.key in equivalent else "")
            for s in found)] if found else []
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softplc.bench.mutate",
                                     description=__doc__.splitlines()[0] if __doc__ else None)
    defaults = Settings()
    parser.add_argument("--seed", type=int, default=defaults.seed)
    parser.add_argument("--sample", type=int, default=defaults.size, help="mutants per module")
    parser.add_argument("--jobs", type=int, default=defaults.jobs)
    parser.add_argument("--budget-s", type=float, default=defaults.budget_s)
    parser.add_argument("--timeout-factor", type=float, default=defaults.timeout_factor)
    parser.add_argument("--module", action="append", default=[],
                        help="only the targets whose path contains this (repeatable)")
    parser.add_argument("--equivalent", type=Path, help="known equivalents: `KEY | reason`")
    parser.add_argument("--json", type=Path, default=Path("build/mutation.json"))
    parser.add_argument("--markdown", type=Path, default=Path("build/mutation.md"))
    args = parser.parse_args(argv)
    settings = Settings(args.seed, args.sample, args.jobs, args.budget_s, args.timeout_factor)
    targets = {p: t for p, t in TARGETS.items()
               if not args.module or any(part in p for part in args.module)}
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, stop)
    start = time.monotonic()
    with committed(Path.cwd()) as root:
        if root != Path.cwd():
            print("mutating the last commit (uncommitted edits are not in it)", file=sys.stderr)
        modules = run(root, targets, settings)
    took_s = time.monotonic() - start
    equivalent = load_equivalent(args.equivalent)
    for out in (args.json, args.markdown):
        out.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({
        "seed": settings.seed, "sample": settings.size, "jobs": settings.jobs,
        "seconds": round(took_s), "modules": [summary(m, equivalent) for m in modules],
    }, indent=1) + "\n", encoding="utf-8")
    text = markdown(modules, equivalent, f"Seed {settings.seed}, {settings.size} mutants per "
                    f"module, {settings.jobs} jobs: {took_s / 60:.1f} min.")
    args.markdown.write_text(text, encoding="utf-8")
    print(text)
    return 1 if any(m.baseline_s is None for m in modules) else 0


if __name__ == "__main__":
    raise SystemExit(main())
