"""Mutated programs for the program fuzz: byte, line and YAML-structure mutations of the real
programs in programs/, from a seeded random generator (reproducible, no shrinking needed:
each mutant is printed with its seed when it fails)."""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = sorted((ROOT / "programs").glob("*.yaml"))

# Values that have broken YAML-driven loaders before: YAML 1.1 booleans, null, huge and
# negative numbers, floats, wrong container types, tags, anchors, odd text, expressions.
WEIRD: list[Any] = [
    None, True, False, 0, -1, 1 << 70, -(1 << 70), 1.5, float("inf"), float("nan"), "", " ",
    "yes", "on", "off", "~", "null", [], {}, [[]], [{}], {"a": None}, [None, 1],
    "a" * 5000, "\u00e9\u20ac\U0001F600", "%QX0.0", "%IW9999", "%MX100.9", "-1s", "1e99s",
    "99999999999999999999 ms", "0ms", "__import__('os')", "().__class__", "a and", "(((",
    "rising(", "tok.__class__", "../../../etc/passwd", "/etc/passwd", "nets/../../x.yaml",
    "t" * 200, {"from": "nowhere"}, {"when": [1]}, {"tokens": "many"}, {"capacity": -3},
]
TOKENS = ["\n", ":", "- ", "{", "}", "[", "]", "&a ", "*a", "!!str ", "!!python/object ", "'",
          '"', "#", "  ", "\t", "? ", "|", ">", "%", "@", "\x00", "\ufeff", "<<: ", ","]


def _mutate_text(rng: random.Random, text: str) -> str:
    kind = rng.randrange(6)
    if not text:
        return rng.choice(TOKENS)
    i = rng.randrange(len(text))
    if kind == 0:  # delete a span
        return text[:i] + text[i + rng.randrange(1, 20):]
    if kind == 1:  # insert a YAML-significant token
        return text[:i] + rng.choice(TOKENS) + text[i:]
    if kind == 2:  # replace a character
        return text[:i] + chr(rng.choice([rng.randrange(32, 127), rng.randrange(0x10000)])) \
            + text[i + 1:]
    lines = text.split("\n")
    j = rng.randrange(len(lines))
    if kind == 3:  # delete a line
        del lines[j]
    elif kind == 4:  # duplicate a line elsewhere
        lines.insert(rng.randrange(len(lines) + 1), lines[j])
    else:  # swap two lines
        k = rng.randrange(len(lines))
        lines[j], lines[k] = lines[k], lines[j]
    return "\n".join(lines)


def _nodes(tree: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    found = [path]
    if isinstance(tree, dict):
        for key, value in tree.items():
            found += _nodes(value, (*path, key))
    elif isinstance(tree, list):
        for index, value in enumerate(tree):
            found += _nodes(value, (*path, index))
    return found


def _set(tree: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    parent = tree
    for step in path[:-1]:
        parent = parent[step]
    parent[path[-1]] = value
    return tree


def _get(tree: Any, path: tuple[Any, ...]) -> Any:
    for step in path:
        tree = tree[step]
    return tree


def _mutate_tree(rng: random.Random, text: str) -> str:
    tree = yaml.safe_load(text)
    paths = _nodes(tree)
    path = rng.choice(paths[1:] or paths)
    kind = rng.randrange(4)
    if kind == 0:  # replace a value with a weird one
        tree = _set(tree, path, rng.choice(WEIRD))
    elif kind == 1 and path:  # drop a key or item
        parent = _get(tree, path[:-1])
        del parent[path[-1]]
    elif kind == 2:  # copy one subtree over another (wrong shape in the right place)
        tree = _set(tree, path, _get(tree, rng.choice(paths)))
    else:  # add an unknown or duplicate-looking key
        node = _get(tree, path)
        if isinstance(node, dict):
            node[rng.choice(["extra", "when", "from", "to", 1, None, True])] = rng.choice(WEIRD)
        else:
            tree = _set(tree, path, [node, node])
    return yaml.safe_dump(tree, sort_keys=False, allow_unicode=True, width=1 << 16)


def mutant(rng: random.Random, text: str) -> str:
    """One to three mutations of `text`; a third of them on the YAML tree."""
    for _ in range(rng.randrange(1, 4)):
        try:
            text = _mutate_tree(rng, text) if rng.random() < 0.33 else _mutate_text(rng, text)
        except (yaml.YAMLError, TypeError, KeyError, IndexError, RecursionError):
            text = _mutate_text(rng, text)  # an earlier mutation broke the YAML itself
    return text
