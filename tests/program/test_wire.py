"""A compiled net crosses processes as data (program/wire.py): what arrives runs exactly as
what left, its expressions compiled again by the sandboxed compiler, never shipped as code."""

from __future__ import annotations

import dataclasses
import pickle
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import pytest

from softplc.core.expr import Compiled, Scope, compile_expr
from softplc.core.net import CompiledNet
from softplc.program import wire
from softplc.program.compiler import compile_file, compile_text
from softplc.runtime.offline.simulate import simulate

ROOT = Path(__file__).resolve().parents[2]
PROGRAMS = sorted((ROOT / "programs").glob("*.yaml"))


def same_value(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b)
    return bool(type(a) is type(b) and a == b)


def assert_same_net(a: CompiledNet, b: CompiledNet) -> None:
    for field in dataclasses.fields(CompiledNet):
        left, right = getattr(a, field.name), getattr(b, field.name)
        assert same_value(left, right), field.name


def ring(transitions: int) -> str:
    lines = ["program: ring", "io_image: ../io_images/transport.yaml", "places:",
             "  p0: {tokens: 1}", *(f"  p{i}: {{}}" for i in range(1, transitions)),
             "transitions:"]
    lines += [f"  t{i}: {{from: [p{i}], to: [p{(i + 1) % transitions}], when: s1_i or not hold}}"
              for i in range(transitions)]
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("path", PROGRAMS, ids=[p.stem for p in PROGRAMS])
def test_every_shipped_program_arrives_as_it_left(path: Path) -> None:
    net = compile_file(path, ROOT)
    assert_same_net(net, wire.loads(wire.dumps(net)))


@pytest.mark.parametrize("name", ["transport", "drilling"])  # cell.yaml drives real devices
def test_an_arrived_net_runs_bit_for_bit_as_the_one_sent(name: str) -> None:
    net = compile_file(ROOT / "programs" / f"{name}.yaml", ROOT)
    arrived = wire.loads(wire.dumps(net))
    # Same plant, same seed: the same trace (guards, actions, token expressions, timers).
    minute = 60 * 10**9
    report = simulate(arrived, minute, seed=5)
    assert report == simulate(net, minute, seed=5)
    assert report["plant"]["faults"] == [] and report["scans"] > 1000


def test_expressions_are_compiled_again_on_arrival_not_shipped() -> None:
    net = compile_file(ROOT / "programs" / "drilling.yaml", ROOT)
    arrived = wire.loads(wire.dumps(net))
    guards = [(t.guard, u.guard) for t, u in zip(net.transitions, arrived.transitions,
                                                  strict=True) if t.guard is not None]
    assert guards
    for sent, got in guards:
        assert got.text == sent.text and got.reads == sent.reads
        assert got.fn is not sent.fn  # a new closure, built here from the text
    # The bytes carry the texts, and no code object or function of the expression compiler.
    blob = b"".join(wire.dumps(net))
    assert b"s1 and not pause" in blob
    assert b"softplc.core.expr\n_Compiler" not in blob and b"code" not in blob.split(b"\n")[0]


def test_long_fields_travel_in_pieces_and_keep_their_types() -> None:
    net = compile_text(ring(1000), str(ROOT / "programs" / "ring.yaml"), ROOT)
    pieces = wire.dumps(net)
    # 1,000 transitions, places, place and transition locations: each in pieces of CHUNK.
    assert len(pieces) > 4 * 1000 // wire.CHUNK
    assert max(map(len, pieces)) < 200_000
    arrived = wire.loads(pieces)
    assert_same_net(net, arrived)
    assert isinstance(arrived.place_index, MappingProxyType)
    with pytest.raises(TypeError):
        arrived.place_index["p0"] = 5  # type: ignore[index]
    # Every guard shares the one scope it was compiled in: the scope crossed once.
    scopes = {id(t.guard.scope) for t in arrived.transitions if t.guard is not None}
    assert len(scopes) == 1


def test_an_expression_without_its_scope_cannot_cross() -> None:
    expr = compile_expr("1 + 2", Scope({}))
    bare = Compiled(expr.text, expr.fn, expr.reads, expr.edges, expr.tokens)
    net = compile_text(ring(3), str(ROOT / "programs" / "ring.yaml"), ROOT)
    t0 = dataclasses.replace(net.transitions[0], guard=bare)
    with pytest.raises(pickle.PicklingError, match="scope"):
        wire.dumps(dataclasses.replace(net, transitions=(t0, *net.transitions[1:])))


def test_what_is_not_a_net_is_refused() -> None:
    net = compile_text(ring(3), str(ROOT / "programs" / "ring.yaml"), ROOT)
    table, _, *rest = wire.dumps(net)
    with pytest.raises(TypeError, match="compiled net"):
        wire.loads((table, pickle.dumps({"not": "a net"}), *rest))


def test_mappings_of_the_net_are_read_only_after_the_trip() -> None:
    net = compile_file(ROOT / "programs" / "transport.yaml", ROOT)
    arrived = wire.loads(wire.dumps(net))
    for field in dataclasses.fields(CompiledNet):
        value = getattr(net, field.name)
        if isinstance(value, MappingProxyType):
            assert isinstance(getattr(arrived, field.name), MappingProxyType), field.name
        elif isinstance(value, Mapping):
            assert isinstance(getattr(arrived, field.name), Mapping), field.name


def test_a_net_loads_a_piece_a_step_with_few_transitions_a_piece() -> None:
    """The scan thread loads a download between scans (runtime/idlework.py): one piece per
    step, and a piece of transitions (each a tree of objects, ~4.5 µs to rebuild) holds at
    most OBJECT_CHUNK of them."""
    net = compile_text(ring(1000), str(ROOT / "programs" / "ring.yaml"), ROOT)
    pieces = wire.dumps(net)
    scopes = pickle.loads(pieces[0])
    loaded = [wire._load(p, scopes) for p in pieces[2:]]
    sizes = [len(chunk) for name, chunk in loaded if name == "transitions"]
    assert sum(sizes) == 1000 and max(sizes) == wire.OBJECT_CHUNK
    loading = wire.loading(pieces)
    steps = 0
    while True:
        try:
            next(loading)
        except StopIteration as done:
            arrived = done.value
            break
        steps += 1
    # The scopes, the head, each piece, then each field joined from its pieces.
    assert steps == len(pieces) + len({name for name, _ in loaded})
    assert_same_net(net, arrived)
