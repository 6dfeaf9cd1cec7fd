"""core/jsonparts.py: a document written in pieces is the text of one json.dumps call, byte
for byte (a retain snapshot's sha256 covers it), and a big dict or list is cut into calls of
CHUNK items (each holds the interpreter lock; one call for a 10,000-place retain snapshot held
it ~2.4 ms, a probe thread beside the writer went without it that long; now ~0.5 ms at most)."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.core.jsonparts import CHUNK, pieces
from softplc.runtime.retain.store import to_bytes


def one_call(value: Any) -> str:
    return json.dumps(value, separators=(",", ":"), sort_keys=True, allow_nan=False)


leaves = st.none() | st.booleans() | st.integers() | st.text(max_size=8) \
    | st.floats(allow_nan=False, allow_infinity=False)
documents = st.recursive(
    leaves,
    lambda inner: st.lists(inner, max_size=12) | st.dictionaries(st.text(max_size=6), inner,
                                                                  max_size=12),
    max_leaves=60)


@settings(max_examples=300, deadline=None)
@given(documents, st.integers(1, 5), st.integers(0, 4))
def test_the_pieces_are_one_calls_text(value: Any, chunk: int, depth: int) -> None:
    assert "".join(pieces(value, depth, chunk)) == one_call(value)


def test_a_big_dict_is_cut_into_calls_of_chunk_items() -> None:
    marking = {f"ring.p{i}": i % 3 for i in range(10_000)}
    payload = {"seq": 1, "marking": marking, "image": {"ix": "AAAA"}, "tokens": {}}
    parts = list(pieces(payload))
    assert "".join(parts) == one_call(payload)
    assert max(p.count(":") for p in parts) <= CHUNK + 1  # no piece holds more items
    assert len(parts) >= 10_000 // CHUNK


def test_what_json_refuses_is_refused_the_same() -> None:
    with pytest.raises(ValueError):
        "".join(pieces({"marking": {f"p{i}": 0 for i in range(CHUNK + 1)}, "x": math.nan}))
    with pytest.raises(TypeError):
        "".join(pieces({"when": object()}))
    mixed = {1: "a", "b": 2}  # non-text keys: one call, as json.dumps writes them
    with pytest.raises(TypeError):
        one_call(mixed)
    with pytest.raises(TypeError):
        "".join(pieces(mixed))


def test_a_retain_snapshot_file_holds_the_same_bytes_as_before() -> None:
    payload = {"seq": 7, "marking": {f"p{i}": i for i in range(3 * CHUNK)}, "state": "RUNNING"}
    head, _, body = to_bytes(payload).partition(b"\n")
    assert body == one_call(payload).encode()
    assert json.loads(head)["length"] == len(body)
