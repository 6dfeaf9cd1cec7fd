"""The YAML values softplc reads, and PyYAML's loader set up to build them (the reference).

Owns: YMap/YList (plain dicts and lists that remember their lines); the loader that builds
them: `on`/`off`/`yes`/`no` stay text (YAML 1.2 booleans only), duplicate keys and keys that
are no plain names become problems, bad literals get a message naming the value. The fast
path (yamlfast.py) takes its resolvers and scalar constructors from here.
Does not know: what a program means, the fast path, the size limits (yamlload.py).
"""

from __future__ import annotations

import re
from typing import Any

import yaml

from softplc.core.problems import Problem

BOOL_TAG = "tag:yaml.org,2002:bool"
YAML11_BOOLS = frozenset({"on", "off", "yes", "no", "y", "n"})


class YMap(dict[Any, Any]):
    """A mapping that knows its own line and the line of each key."""

    line: int = 0
    lines: dict[Any, int]


class YList(list[Any]):
    line: int = 0
    lines: list[int]


class Loader(yaml.SafeLoader):
    problems: list[Problem]
    filename: str

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, LookupError, AttributeError) as exc:
            if not isinstance(node, yaml.ScalarNode):
                raise
            # `0x_`, `2024-13-45` resolve as a number or date there is no such; `!!int ''`
            raise yaml.constructor.ConstructorError(
                None, None, _bad_literal(node, exc), node.start_mark) from None


def _bad_literal(node: yaml.Node, exc: Exception) -> str:
    kind = str(node.tag).rsplit(":", 1)[-1]
    return f"{repr(node.value)[:40]} is not a valid {kind} ({exc})"


Loader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != BOOL_TAG]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
Loader.add_implicit_resolver(
    BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def _mapping(loader: Loader, node: yaml.MappingNode) -> YMap:
    out = YMap()
    out.line = node.start_mark.line + 1
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        problem = key_problem(out, key, line, loader.filename)
        if problem is not None:
            loader.problems.append(problem)
            continue
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = line
    return out


def key_problem(out: YMap, key: Any, line: int, filename: str) -> Problem | None:
    """Why `key` cannot go into `out`, or None (its value is then never constructed)."""
    if not isinstance(key, str | int | bool):
        return Problem(filename, line, "", "keys must be plain names")
    if key in out:
        return Problem(filename, line, str(key),
                       f"duplicate key {key!r} (first at line {out.lines[key]})")
    return None


def _sequence(loader: Loader, node: yaml.SequenceNode) -> YList:
    out = YList(loader.construct_object(child, deep=True) for child in node.value)
    out.line = node.start_mark.line + 1
    out.lines = [child.start_mark.line + 1 for child in node.value]
    return out


Loader.add_constructor("tag:yaml.org,2002:map", _mapping)
Loader.add_constructor("tag:yaml.org,2002:seq", _sequence)
