"""Program fuzz: mutated real programs and hypothesis-built ones into `check` (compile_text)
and into a download to a running PLC. Never a crash: only ProgramError, every problem
located (FILE:LINE: ...); a refused download leaves the running program, its state and
(when stopped) its marking exactly as they were."""

from __future__ import annotations

import random
import re

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softplc.core.lifecycle import Command
from softplc.core.problems import ProgramError
from softplc.program.compiler import compile_text
from tests.fuzz import budget
from tests.fuzz.live import LivePlc
from tests.fuzz.mutate import PROGRAMS, ROOT, mutant
from tests.support import eventually

LOCATED = re.compile(r"^[^\s:][^:]*:\d+: \S")


def check(text: str, filename: str) -> tuple[bool, list[str]]:
    """(accepted, problems): anything but ProgramError propagates and fails the test."""
    try:
        compile_text(text, filename, ROOT)
    except ProgramError as error:
        problems = [str(p) for p in error.problems]
        assert problems, "a ProgramError without problems"
        for problem in problems:
            assert LOCATED.match(problem) and "\n" not in problem, problem
        return False, problems
    return True, []


def test_mutated_programs_get_located_problems_never_a_crash() -> None:
    rng = random.Random(budget.seed(1234))
    texts = {path: path.read_text() for path in PROGRAMS}
    n, accepted, problems = budget.scaled(150), 0, 0
    for i in range(n):
        path = rng.choice(PROGRAMS)
        text = mutant(rng, texts[path])
        try:
            ok, found = check(text, str(path))
        except Exception as exc:
            raise AssertionError(f"mutant {i} of {path.name} crashed the compiler:\n{text}") \
                from exc
        accepted += ok
        problems += len(found)
    budget.record("programs.check_mutants", programs=n, accepted=accepted,
                  rejected=n - accepted, problems=problems, crashes=0)


NAMES = st.sampled_from(["a", "b", "c", "idle", "busy", "m1", "s1_i", "hold", "x.y", "", "1",
                         "__class__", "on", "no"])
EXPRS = st.one_of(
    st.sampled_from(["s1_i", "not s1_i and hold", "rising(s1_o)", "parts_delivered > 3",
                     "tok.id == 1", "s1_i and", "(((", "1 / 0", "__import__('os')",
                     "9" * 30, "x := 1", "'a' * 5", "rising(m1)", "min(1)"]),
    st.text(max_size=30),
)
SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-5, 5), st.integers(),
                    st.text(max_size=12), st.sampled_from(["1s", "500ms", "-1s", "1e9s", "x"]))
PLACE = st.fixed_dictionaries({}, optional={
    "tokens": st.one_of(SCALARS, st.lists(st.dictionaries(NAMES, SCALARS, max_size=2),
                                          max_size=2)),
    "capacity": SCALARS, "outputs": st.one_of(SCALARS, st.lists(NAMES, max_size=2)),
    "coloured": SCALARS, "extra": SCALARS})
ARC = st.one_of(NAMES, st.dictionaries(st.sampled_from(["place", "weight", "var", "kind"]),
                                       st.one_of(NAMES, SCALARS), max_size=3))
TRANSITION = st.fixed_dictionaries({}, optional={
    "from": st.one_of(SCALARS, st.lists(ARC, max_size=3)),
    "to": st.one_of(SCALARS, st.lists(ARC, max_size=3)),
    "when": st.one_of(EXPRS, SCALARS), "delay": SCALARS, "priority": SCALARS,
    "set": st.one_of(SCALARS, st.dictionaries(NAMES, st.one_of(EXPRS, SCALARS), max_size=2)),
    "emit": st.one_of(SCALARS, NAMES)})
PROGRAM = st.fixed_dictionaries(
    {"program": st.one_of(NAMES, SCALARS)},
    optional={"io_image": st.sampled_from(["../io_images/transport.yaml", "/etc/passwd",
                                           "../../x.yaml", "nets/conveyor.yaml", ""]),
              "places": st.one_of(SCALARS, st.dictionaries(NAMES, PLACE, max_size=4)),
              "transitions": st.one_of(SCALARS, st.dictionaries(NAMES, TRANSITION, max_size=4)),
              "events": st.one_of(SCALARS, st.lists(NAMES, max_size=2)),
              "subnets": st.dictionaries(NAMES, st.dictionaries(
                  st.sampled_from(["net", "with"]), st.one_of(
                      st.sampled_from(["nets/conveyor.yaml", "nets/none.yaml", "../../x"]),
                      st.dictionaries(NAMES, NAMES, max_size=2), SCALARS), max_size=2),
                  max_size=2)})


def test_generated_programs_get_located_problems_never_a_crash() -> None:
    tried = {"programs": 0, "accepted": 0}

    @settings(max_examples=budget.scaled(150), derandomize=True, deadline=None, database=None,
              suppress_health_check=list(HealthCheck))
    @given(program=PROGRAM)
    def run(program: dict[str, object]) -> None:
        text = yaml.safe_dump(program, sort_keys=False, allow_unicode=True)
        ok, _ = check(text, str(ROOT / "programs" / "generated.yaml"))
        tried["programs"] += 1
        tried["accepted"] += ok

    run()
    budget.record("programs.check_generated", **tried, crashes=0)


def _state(plc: LivePlc) -> tuple[str, str, dict[str, object]]:
    document = plc.settled()
    return document["state"], document["program_hash"], document["marking"]


def test_refused_downloads_leave_the_running_program_untouched() -> None:
    rng = random.Random(budget.seed(99))
    original = (ROOT / "programs" / "transport.yaml").read_text()
    n, refused, accepted_skipped = budget.scaled(30), 0, 0
    with LivePlc(ROOT, ROOT / "programs" / "transport.yaml") as plc:
        eventually(lambda: plc.document().get("state") == "RUNNING")
        for i in range(n):
            text = mutant(rng, original)
            ok, _ = check(text, str(ROOT / "programs" / "transport.yaml"))
            if ok:
                accepted_skipped += 1  # a valid program: a download would rightly replace it
                continue
            stopped = i % 2 == 1
            if stopped:
                assert plc.command(Command.STOP).ok
            state, program_hash, marking = _state(plc)
            reply = plc.command(Command.DOWNLOAD, text, "transport.yaml", online=not stopped)
            assert not reply.ok
            assert reply.message.startswith("download refused:\n"), reply.message
            assert "internal compiler error" not in reply.message
            lines = reply.message.splitlines()[1:]
            assert lines and all(LOCATED.match(line) for line in lines), reply.message
            after_state, after_hash, after_marking = _state(plc)
            assert (after_state, after_hash) == (state, program_hash)
            if stopped:
                assert after_marking == marking
                assert plc.command(Command.RESUME).ok
            refused += 1
    budget.record("programs.download_mutants", programs=n, refused=refused,
                  valid_not_sent=accepted_skipped, crashes=0, program_changed=0)
