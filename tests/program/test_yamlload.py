"""The YAML loader: its fast path (libyaml's or PyYAML's events, built without recursion)
gives exactly what PyYAML's own composer and constructor give, lines and problems included;
deep, bomb-like or odd documents are located problems, never a crash."""

from __future__ import annotations

import math
import random
from pathlib import Path
from typing import Any

import pytest
import yaml

from softplc.bench.netgen import ring, to_yaml
from softplc.core.problems import Problem, ProgramError
from softplc.program import yamlload
from softplc.program.compiler import compile_text
from softplc.program.yamlload import YList, YMap, load_yaml
from tests.fuzz.mutate import PROGRAMS, mutant

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted(p for d in ("programs", "io_images", "tests/program/bad") for p in
               (ROOT / d).rglob("*.yaml"))
# YAML-significant pieces, including those where libyaml and PyYAML disagree.
PIECES = ["a", "b", "1", "007", "0x_", "2024-13-45", " ", "\n", "\n  ", ": ", ":", "- ", "{",
          "}", "[", "]", ", ", "?", "? ", "\t", "#", " #", "'", '"', "&x ", "*x", "!",
          "!!int ", "|", ">", "%", "~", "---", "...", "\r\n", "\x85", "\ufeff", "<<", "true",
          "on", "null", "1.5", "{a: 1, a: 2}"]


def shape(value: Any) -> Any:
    """Everything the loader promises: values with their types, and every line."""
    if isinstance(value, YMap):
        return ("map", value.line, [(shape(k), value.lines[k], shape(v)) for k, v in value.items()])
    if isinstance(value, YList):
        return ("list", value.line, value.lines, [shape(v) for v in value])
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    return (type(value).__name__, value)


def assert_same_as_pyyaml(text: str) -> None:
    data, problems = yamlload._load(text, "f.yaml")  # load_yaml's parse, before % hints
    ref_data, ref_problems = yamlload._reference(text, "f.yaml")
    assert (shape(data), sorted(problems)) == (shape(ref_data), sorted(ref_problems)), repr(text)


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_yaml_file_loads_as_pyyaml_loads_it(path: Path) -> None:
    assert_same_as_pyyaml(path.read_text(encoding="utf-8"))


def test_mutated_programs_load_as_pyyaml_loads_them() -> None:
    rng = random.Random(2024)
    texts = [p.read_text(encoding="utf-8") for p in PROGRAMS]
    for _ in range(300):
        assert_same_as_pyyaml(mutant(rng, rng.choice(texts)))


def test_odd_snippets_load_as_pyyaml_loads_them() -> None:
    rng = random.Random(7)
    for _ in range(3000):
        assert_same_as_pyyaml("".join(rng.choice(PIECES) for _ in range(rng.randrange(1, 14))))


@pytest.mark.parametrize("text", [
    "t: {from: [c2.full, {place: deliv?red, var: d}]}\n",  # libyaml reads a scalar here
    "t: {from: [a, {place: b, va\tr: c}]}\n",  # libyaml skips the tab
    "a: |#\n  x\n",
    "a:\n  - \n  - b\n",  # libyaml marks an empty item on the next line
    "a: ! 1\n",
    "a: !!int 12\nb: !!str 5\n",
    "a: &x [1, 2]\nb: *x\nc: &y 3\nd: *y\n",
    "a: &x [1, *x]\n",  # recursive: the reference loader's error
    "{1: a, true: b}\n",
    "a: {a: 1, a: {b: 1, b: 2}}\n",  # the dropped value's own problems are not reported
    "? [a, b]\n: c\n",
    "--- a\n--- b\n",
    "",
    "# only a comment?\n",
], ids=repr)
def test_known_differences_between_libyaml_and_pyyaml_do_not_show(text: str) -> None:
    assert_same_as_pyyaml(text)


def test_without_libyaml_pyyaml_events_give_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(yamlload, "_CParser", None)
    for path in FILES:
        assert_same_as_pyyaml(path.read_text(encoding="utf-8"))
    assert_same_as_pyyaml("a: " + "[" * 1000 + "]" * 1000)


def nested_flow(depth: int) -> str:
    return "a: " + "[" * depth + "]" * depth


def nested_block(depth: int) -> str:
    return "".join(" " * i + f"k{i}:\n" for i in range(depth)) + " " * depth + "x: 1\n"


@pytest.mark.parametrize("text", [
    nested_flow(1000), nested_flow(5000), "a: " + "{a: " * 3000 + "1" + "}" * 3000,
    nested_block(1000), "a: !!str x\nb: " + "[" * 5000 + "]" * 5000,
    "places: {}\nb: " + "[" * 100_000,  # unclosed: refused before the syntax error
], ids=["flow-1000", "flow-5000", "maps-3000", "block-1000", "after-a-tag", "flow-100000"])
def test_deep_nesting_is_refused_as_a_located_problem(text: str) -> None:
    assert load_yaml(text, "f.yaml") == (None, [Problem("f.yaml", 1, "",
                                                        "YAML error: nesting too deep")])


def test_nesting_up_to_the_limit_loads() -> None:
    data, problems = load_yaml(nested_flow(yamlload.MAX_NESTING - 1), "f.yaml")
    assert problems == [] and isinstance(data, YMap)


@pytest.mark.parametrize(("text", "line", "reason"), [
    ("a: 1\nb: 2024-13-45\n", 2, "'2024-13-45' is not a valid timestamp (month must be in 1..12)"),
    ("a: 0x_\n", 1, "'0x_' is not a valid int"),
    ("a:\n  - !!int ''\n", 2, "'' is not a valid int"),
])
def test_a_literal_that_resolves_to_no_value_is_a_located_problem(text: str, line: int,
                                                                  reason: str) -> None:
    data, problems = load_yaml(text, "f.yaml")
    assert data is None
    assert [(p.line, p.message.split(" (")[0] if "(" not in reason else p.message)
            for p in problems] == [(line, f"YAML syntax error: {reason}")]


def test_a_big_net_written_out_in_full_is_not_an_alias_bomb(tmp_path: Path) -> None:
    """Its 10,000 transitions are more than 100,000 values: only what aliases add counts."""
    (tmp_path / "io.yaml").write_text("symbols: {}\n", encoding="utf-8")
    net = compile_text(to_yaml(ring(10_000), "io.yaml"), str(tmp_path / "net.yaml"))
    assert len(net.transitions) == 10_000
    # after 3 header lines, 10,000 places and `transitions:`
    assert [t.line for t in net.transitions[:2]] == [10_005, 10_006]


def test_an_alias_bomb_in_a_big_net_is_still_refused(tmp_path: Path) -> None:
    (tmp_path / "io.yaml").write_text("symbols: {}\n", encoding="utf-8")
    laughs = ["lol:", "  a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    laughs += [f"  a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 7)]
    text = to_yaml(ring(2000), "io.yaml") + "\n".join(laughs) + "\n"
    with pytest.raises(ProgramError) as info:
        compile_text(text, str(tmp_path / "net.yaml"))
    assert [p.message for p in info.value.problems] == [
        "YAML error: more than 100000 values once aliases are expanded"]


def test_the_fast_path_is_libyaml_here() -> None:
    """The speed this module is for: the dev environment has libyaml."""
    assert yaml.__with_libyaml__ and yamlload._CParser is not None
