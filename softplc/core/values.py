"""The values a program can carry: what a coloured token's field may hold.

Owns: the value types of the language (integers in the expression range, finite IEEE 754
doubles, booleans, text up to MAX_TEXT characters), the rules for a token record (identifier
field names, at most MAX_FIELDS fields), and a description of anything else for a located
problem or a fault reason.
Does not know: YAML, files, where a value came from (the caller adds FILE:LINE or the
transition).

Why these and nothing else: every value must survive, unchanged, the expression language
(integer and floating-point arithmetic, comparison, text equality), the retain file (JSON) and
the Modbus and HTTP views. A fraction is an lreal (issue 30: before, integer arithmetic
truncated `1.5` to 1); NaN and infinities are not JSON and not values; a date or a null is not
JSON, a list or a nested mapping cannot be compared or shown as one cell.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from softplc.core.expr import INT_LIMIT, MAX_STR

MAX_TEXT = MAX_STR  # characters of one text value: a part id, a recipe name, a message
MAX_FIELDS = 32  # fields of one token record
MAX_FIELD_NAME = 64  # characters of a field name


def describe(value: object) -> str:
    """What a value that is not a token value is, in the words of a program's author."""
    if value is None:
        return "null (an empty value)"
    if isinstance(value, float):
        return f"the number {value!r}"
    isoformat = getattr(value, "isoformat", None)  # a date or time a loader produced
    if callable(isoformat):
        return f"the date {isoformat()}"
    if isinstance(value, list | tuple):
        return "a list"
    if isinstance(value, Mapping):
        return "a nested mapping"
    if isinstance(value, bytes | bytearray):
        return "binary data"
    return f"a value of type {type(value).__name__}"


def value_problem(value: object) -> str | None:
    """None for a value the runtime can carry, else what is wrong with it."""
    kind = type(value)
    if kind is bool:
        return None
    if kind is int:
        if -INT_LIMIT < value < INT_LIMIT:  # type: ignore[operator]
            return None
        return f"integer {value} is out of range (|n| < 2**63)"
    if kind is float:
        if math.isfinite(value):  # type: ignore[arg-type]
            return None
        return f"{value!r} is not a finite number"
    if kind is str:
        if len(value) <= MAX_TEXT:  # type: ignore[arg-type]
            return None
        return f"text of {len(value)} characters (at most {MAX_TEXT})"  # type: ignore[arg-type]
    return (f"{describe(value)} is not a token value: use a number, true/false or "
            f"'text' (at most {MAX_TEXT} characters)")


def field_name_problem(name: object) -> str | None:
    """None for a field name an expression can read (`p.name`), else what is wrong."""
    if not isinstance(name, str) or not name.isidentifier():
        return f"field name {name!r} is not a name (letters, digits, _; not starting with a digit)"
    if name.startswith("_"):
        return f"field name {name!r} starts with _ (expressions cannot read it)"
    if len(name) > MAX_FIELD_NAME:
        return f"field name of {len(name)} characters (at most {MAX_FIELD_NAME})"
    return None


def record_problems(record: object) -> list[tuple[object, str]]:
    """(field name or None, what is wrong) for each problem of one token record."""
    if not isinstance(record, Mapping):
        return [(None, f"{describe(record)} is not a token record: write {{field: value}}")]
    found: list[tuple[object, str]] = []
    if len(record) > MAX_FIELDS:
        found.append((None, f"a record of {len(record)} fields (at most {MAX_FIELDS})"))
    for name, value in record.items():
        problem = field_name_problem(name)
        if problem is None:
            problem = value_problem(value)
            if problem is not None:
                problem = f"field {name}: {problem}"
        if problem is not None:
            found.append((name, problem))
    return found
