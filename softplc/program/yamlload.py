"""YAML with line numbers and without YAML 1.1 traps: the one entry, `load_yaml`.

Owns: choosing the loader (the fast path of yamlfast.py, else PyYAML's own loader as set up
in yamlref.py, which decides every odd or faulty document); the limit on what aliases expand
to; located problems for unreadable text; the helpers callers use on the loaded values
(line_of, trap_hint).
Does not know: what a program means.
"""

from __future__ import annotations

from typing import Any

import yaml

from softplc.core.problems import Problem
from softplc.program.yamlfast import (
    MAX_NESTING,
    NON_PRINTABLE,
    PyEvents,
    TooDeep,
    Unsupported,
    build,
    libyaml_agrees,
)
from softplc.program.yamlfast import CParser as _CParser
from softplc.program.yamlref import YAML11_BOOLS, Loader, YList, YMap

# What callers import from here (the loaded values' types, the nesting limit).
__all__ = ["MAX_EXPANDED_VALUES", "MAX_NESTING", "YList", "YMap", "line_of", "load_yaml",
           "trap_hint"]

MAX_EXPANDED_VALUES = 100_000  # the example programs have a few hundred
_PERCENT = "found character '%' that cannot start any token"


MAX_PERCENT_HINTS = 20  # unquoted %addresses reported (each a parse again) before giving up


def load_yaml(text: str, filename: str) -> tuple[Any, list[Problem]]:
    """Parse `text`. Returns (data, problems); data is None when the text does not parse.
    An unquoted `%IX0.0` (YAML reserves `%`) is one located problem, and the rest of the
    file is still read as if it were quoted, so its other problems are reported too."""
    hints: list[Problem] = []
    while True:
        at: list[tuple[int, int]] = []
        data, problems = _load(text, filename, at)
        if not at:
            return data, hints + problems if hints else problems
        (line, column), lines = at[0], text.split("\n")
        row = lines[line] if line < len(lines) else ""
        if row[column:column + 1] != "%":  # other line breaks (\r, U+0085) than \n
            data, problems = _load(text, filename)  # the scanner's message, not the hint
            return data, hints + problems
        end = column
        while end < len(row) and row[end] not in " ,]}#\t":
            end += 1
        word = row[column:end]
        hints.append(Problem(filename, line + 1, "", f"unquoted {word}: YAML reserves % at "
                             f"the start of a value; write \"{word}\""))
        if len(hints) == MAX_PERCENT_HINTS:
            return None, hints
        lines[line] = f'{row[:column]}"{word}"{row[end:]}'
        text = "\n".join(lines)


def _load(text: str, filename: str, percent: list[tuple[int, int]] | None = None
          ) -> tuple[Any, list[Problem]]:
    """load_yaml's one parse: the fast path, else the reference loader (same results)."""
    if NON_PRINTABLE.search(text) is None:  # else the reader's exact message below
        source = _CParser if _CParser is not None and libyaml_agrees(text) else PyEvents
        try:
            built = build(source, text, filename)
        except TooDeep:
            return None, [Problem(filename, 1, "", "YAML error: nesting too deep")]
        except Unsupported:
            built = None  # the reference loader decides, with its own messages
        if built is not None:
            return _checked(built.data, built.expanded, built.own, built.problems, filename)
    return _reference(text, filename, percent)


def _reference(text: str, filename: str, percent: list[tuple[int, int]] | None = None
               ) -> tuple[Any, list[Problem]]:
    """`percent`: given, an unquoted % puts its (line, column) there instead of a problem."""
    """PyYAML's own composer and constructor: the behaviour yamlfast.build reproduces, used for
    what it does not handle (explicit tags, errors, several documents)."""
    try:
        loader = Loader(text)  # the reader rejects control characters at once
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
        if percent is not None and mark is not None and str(exc.problem).startswith(_PERCENT):
            percent.append((mark.line, mark.column))
            return None, []
        line = mark.line + 1 if mark is not None else 1
        reason = exc.problem or str(exc)
        return None, [Problem(filename, line, "", f"YAML syntax error: {reason}")]
    except yaml.YAMLError as exc:
        return None, [_unreadable(exc, text, filename)]
    finally:
        loader.dispose()
    expanded, own = _expanded_size(data)
    return _checked(data, expanded, own, loader.problems, filename)


def _checked(data: Any, expanded: int, own: int, problems: list[Problem],
             filename: str) -> tuple[Any, list[Problem]]:
    if expanded - own > MAX_EXPANDED_VALUES:
        # Aliases share one object: `&a [x, x]`, `&b [*a, *a]`, ... is small text and tiny
        # memory, but anything that walks it walks 10**9 values (a "billion laughs"). Only
        # what aliases add counts: a big net written out in full is not a bomb.
        return None, [Problem(filename, 1, "", f"YAML error: more than {MAX_EXPANDED_VALUES} "
                              "values once aliases are expanded")]
    return data, problems


def _expanded_size(data: Any) -> tuple[int, int]:
    """(values a walk of `data` visits with every alias expanded, values as written: each
    shared object once). Computed once per shared object, so it costs the real size."""
    sizes: dict[int, int] = {}
    own = 0
    stack: list[tuple[Any, bool]] = [(data, False)]
    while stack:
        value, children_done = stack.pop()
        if not isinstance(value, dict | list) or id(value) in sizes:
            continue
        children = [*value.keys(), *value.values()] if isinstance(value, dict) else value
        if children_done:
            sizes[id(value)] = 1 + sum(sizes.get(id(c), 1) for c in children)
            own += 1 + sum(1 for c in children if not isinstance(c, dict | list))
            continue
        stack.append((value, True))
        stack.extend((c, False) for c in children)
    return sizes.get(id(data), 1), own if sizes else 1


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
