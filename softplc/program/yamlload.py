"""YAML with line numbers and without YAML 1.1 traps.

Owns: loading YAML text into plain dicts/lists/scalars that remember their line numbers;
`on`/`off`/`yes`/`no` stay text (YAML 1.2 booleans only), duplicate keys are problems.
Does not know: what a program means.
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


class _Loader(yaml.SafeLoader):
    problems: list[Problem]
    filename: str


_Loader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != BOOL_TAG]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(
    BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def _mapping(loader: _Loader, node: yaml.MappingNode) -> YMap:
    out = YMap()
    out.line = node.start_mark.line + 1
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        if not isinstance(key, str | int | bool):
            loader.problems.append(Problem(loader.filename, line, "", "keys must be plain names"))
            continue
        if key in out:
            loader.problems.append(
                Problem(loader.filename, line, str(key),
                        f"duplicate key {key!r} (first at line {out.lines[key]})")
            )
            continue
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = line
    return out


def _sequence(loader: _Loader, node: yaml.SequenceNode) -> YList:
    out = YList(loader.construct_object(child, deep=True) for child in node.value)
    out.line = node.start_mark.line + 1
    out.lines = [child.start_mark.line + 1 for child in node.value]
    return out


_Loader.add_constructor("tag:yaml.org,2002:map", _mapping)  # type: ignore[arg-type]
_Loader.add_constructor("tag:yaml.org,2002:seq", _sequence)  # type: ignore[arg-type]


MAX_EXPANDED_VALUES = 100_000  # the example programs have a few hundred


def load_yaml(text: str, filename: str) -> tuple[Any, list[Problem]]:
    """Parse `text`. Returns (data, problems); data is None when the text does not parse."""
    try:
        loader = _Loader(text)  # the reader rejects control characters in the first chunk
    except yaml.YAMLError as exc:
        return None, [_unreadable(exc, text, filename)]
    loader.problems = []
    loader.filename = filename
    try:
        data = loader.get_single_data()
    except RecursionError:  # PyYAML composes recursively: `[[[[...` a thousand deep
        return None, [Problem(filename, 1, "", "YAML error: nesting too deep")]
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else 1
        reason = exc.problem or str(exc)
        return None, [Problem(filename, line, "", f"YAML syntax error: {reason}")]
    except yaml.YAMLError as exc:  # the reader checks later chunks while parsing
        return None, [_unreadable(exc, text, filename)]
    finally:
        loader.dispose()
    expanded = _expanded_size(data)
    if expanded > MAX_EXPANDED_VALUES:
        # Aliases share one object: `&a [x, x]`, `&b [*a, *a]`, ... is small text and tiny
        # memory, but anything that walks it walks 10**9 values (a "billion laughs").
        return None, [Problem(filename, 1, "", f"YAML error: more than {MAX_EXPANDED_VALUES} "
                              "values once aliases are expanded")]
    return data, loader.problems


def _expanded_size(data: Any) -> int:
    """How many values a walk of `data` visits, every alias expanded; computed once per
    shared object, so it costs the document's real size. Saturates past the limit."""
    sizes: dict[int, int] = {}
    stack: list[tuple[Any, bool]] = [(data, False)]
    while stack:
        value, children_done = stack.pop()
        if not isinstance(value, dict | list) or id(value) in sizes:
            continue
        children = [*value.keys(), *value.values()] if isinstance(value, dict) else value
        if children_done:
            total = 1 + sum(sizes.get(id(c), 1) for c in children)
            sizes[id(value)] = min(total, MAX_EXPANDED_VALUES + 1)
            continue
        stack.append((value, True))
        stack.extend((c, False) for c in children)
    return sizes.get(id(data), 1)


def _unreadable(exc: yaml.YAMLError, text: str, filename: str) -> Problem:
    """One located line for an error without a mark (PyYAML's reader gives a position
    and a multi-line message)."""
    if isinstance(exc, yaml.reader.ReaderError):
        line = text.count("\n", 0, max(exc.position, 0)) + 1
        char = exc.character if isinstance(exc.character, int) else ord(exc.character)
        return Problem(filename, line, "", f"YAML error: character U+{char:04X} is not allowed "
                       "in YAML")
    return Problem(filename, 1, "", "YAML error: " + " ".join(str(exc).split()))


def line_of(container: Any, key: Any, default: int = 0) -> int:
    if isinstance(container, YMap):
        return container.lines.get(key, container.line)
    if isinstance(container, YList) and isinstance(key, int) and key < len(container.lines):
        return container.lines[key]
    return getattr(container, "line", default)


def trap_hint(value: Any) -> str:
    """A hint when a YAML 1.1 boolean word was used where YAML 1.2 reads text."""
    if isinstance(value, str) and value.lower() in YAML11_BOOLS:
        return f" ({value!r} is text here, not a boolean: write true or false)"
    return ""
