"""A big JSON document written a piece at a time, the same text one `json.dumps` call makes.

Owns: `pieces`, the JSON of a value as `json.dumps(value, separators=(",", ":"),
sort_keys=True, allow_nan=False)` writes it, cut so that no single `json.dumps` call encodes
more than CHUNK items of a dict or list. Why: a thread of the scan process that encodes a
document (the retain writer) holds the interpreter lock for the whole of each C call, and
the scan cannot start its slot meanwhile; a 10,000-place net's retain snapshot was one call
of ~2.4 ms (the scan's next slot missed twice a second at 1 ms), and between pieces the
scan takes the lock back within the switch interval.
Does not know: what the document means, files, threads.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any, Final

CHUNK: Final = 256  # items of a dict or list per json.dumps call
_ENCODE = json.JSONEncoder(separators=(",", ":"), sort_keys=True, allow_nan=False).encode


def pieces(value: Any, depth: int = 3, chunk: int = CHUNK) -> Iterator[str]:
    """The JSON text of `value` in pieces (their concatenation is that of one call), down to
    `depth` levels of dicts and lists; raises what json.dumps raises (ValueError for a NaN,
    TypeError for what JSON cannot hold)."""
    if depth > 0 and isinstance(value, dict) and value and all(isinstance(k, str) for k in value):
        keys = sorted(value)  # the keys alone: sorting 10,000 (key, value) pairs took ~1 ms
        yield "{"
        if any(_big(v, chunk) for v in value.values()):  # a value to cut in turn: key by key
            for i, key in enumerate(keys):
                yield ("," if i else "") + _ENCODE(key) + ":"
                yield from pieces(value[key], depth - 1, chunk)
        else:
            for i in range(0, len(keys), chunk):
                part = {key: value[key] for key in keys[i:i + chunk]}
                yield ("," if i else "") + _ENCODE(part)[1:-1]
        yield "}"
    elif depth > 0 and isinstance(value, list) and len(value) > chunk:
        yield "["
        for i in range(0, len(value), chunk):
            yield ("," if i else "") + _ENCODE(value[i:i + chunk])[1:-1]
        yield "]"
    else:
        yield _ENCODE(value)


def _big(value: Any, chunk: int) -> bool:
    return isinstance(value, (dict, list)) and len(value) > chunk
