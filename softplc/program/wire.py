"""A compiled net as bytes, to cross from the compile process to the scan process.

Owns: `dumps` and `loads` of a CompiledNet (pickle, protocol 5, with a private dispatch
table, in pieces): read-only mappings travel as dicts and come back read-only; a compiled
expression travels as its text and scope and is compiled again on arrival by the same
sandboxed compiler (core/expr.py), so no code object or closure ever crosses, only data the
allowlist checks.
Why pickle: the scan process must end with Python objects; rebuilding them from pickle's
opcodes is the cheapest way there (10,000 transitions: ~50 ms, gc off, against ~320 ms to
compile the YAML), and it goes a piece at a time (`loading`), so the scan thread loads a
download between its scans (runtime/download.py).
Trust: the bytes come from the runtime's own compile process over a private pipe, never from
a client; `loads` is not for bytes of unknown origin.
Does not know: files, processes, the scan.
"""

from __future__ import annotations

import copyreg
import dataclasses
import io
import pickle
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from softplc.core.expr import Compiled, Scope, compile_expr
from softplc.core.net import CompiledNet
from softplc.core.steps import Steps, drain


def _read_only(items: dict[Any, Any]) -> Mapping[Any, Any]:
    return MappingProxyType(items)


def _reduce_proxy(proxy: MappingProxyType[Any, Any]) -> tuple[Any, ...]:
    return _read_only, (dict(proxy),)


def _reduce_compiled(expr: Compiled) -> tuple[Any, ...]:
    scope = expr.scope
    if scope is None:
        raise pickle.PicklingError(f"expression {expr.text!r} carries no scope to rebuild from")
    return compile_expr, (expr.text, scope)  # compiled again, through the allowlist


_TABLE = copyreg.dispatch_table.copy()
_TABLE[MappingProxyType] = _reduce_proxy
_TABLE[Compiled] = _reduce_compiled
Piece = bytes | memoryview  # a view: a piece still in the buffer it arrived in (replyfile.py)
CHUNK = 256  # entries of a long field per piece: a place's entry loads in ~0.1 µs ...
OBJECT_CHUNK = 32  # ... a transition (a tree of objects) in ~4.5 µs: ~150 µs a piece


class _Pickler(pickle.Pickler):
    """Scopes (shared by many expressions, and each holding every symbol's name) travel once,
    in a table of their own; each piece refers to them by index."""

    def __init__(self, buffer: io.BytesIO, scopes: dict[int, tuple[int, Scope]]) -> None:
        super().__init__(buffer, protocol=5)
        self.dispatch_table = _TABLE
        self.scopes = scopes

    def persistent_id(self, obj: Any) -> int | None:
        if type(obj) is not Scope:
            return None
        known = self.scopes.setdefault(id(obj), (len(self.scopes), obj))
        return known[0]


class _Unpickler(pickle.Unpickler):
    def __init__(self, data: Piece, scopes: list[Scope]) -> None:
        super().__init__(io.BytesIO(data))
        self.scopes = scopes

    def persistent_load(self, pid: Any) -> Scope:
        scope: Scope = self.scopes[pid]
        return scope


def _dump(obj: Any, scopes: dict[int, tuple[int, Scope]]) -> bytes:
    buffer = io.BytesIO()
    _Pickler(buffer, scopes).dump(obj)
    return buffer.getvalue()


def _load(data: Piece, scopes: list[Scope]) -> Any:
    return _Unpickler(data, scopes).load()


def dumps(net: CompiledNet) -> tuple[bytes, ...]:
    """The net in pieces: the scope table, the net without its long fields, then each long
    field (the transitions, every per-place table) CHUNK entries at a time.

    Why pieces: unpickling builds each container in one C stretch that nothing can
    interrupt, and frees what its memo held only at the end; for a 10,000-transition net in
    one piece that was a 1.3 ms stretch building a per-place table and 5 ms freeing the
    transitions' temporary states, at a scan period of 1 ms. A piece loads in ~150 µs at
    most: one step of `loading` between two scans."""
    scopes: dict[int, tuple[int, Scope]] = {}
    long_fields: dict[str, Any] = {}
    pieces: list[bytes] = []
    for f in dataclasses.fields(net):
        value = getattr(net, f.name)
        if isinstance(value, tuple) and len(value) > CHUNK:
            long_fields[f.name] = ()
            size = OBJECT_CHUNK if f.name == "transitions" else CHUNK
            pieces += [_dump((f.name, value[i:i + size]), scopes)
                       for i in range(0, len(value), size)]
        elif isinstance(value, Mapping) and len(value) > CHUNK:
            long_fields[f.name] = MappingProxyType({}) if isinstance(value, MappingProxyType) \
                else {}
            items = list(value.items())
            pieces += [_dump((f.name, dict(items[i:i + CHUNK])), scopes)
                       for i in range(0, len(items), CHUNK)]
    head = _dump(dataclasses.replace(net, **long_fields), scopes)
    table = pickle.dumps([scope for _, scope in scopes.values()], protocol=5)  # index order
    return (table, head, *pieces)


def loads(pieces: tuple[Piece, ...]) -> CompiledNet:
    return drain(loading(pieces))


def loading(pieces: tuple[Piece, ...]) -> Steps[CompiledNet]:
    """loads(), a piece a step (core/steps.py): the scan thread loads a download between
    scans."""
    scopes = pickle.loads(pieces[0])
    yield
    net = _load(pieces[1], scopes)
    if not isinstance(net, CompiledNet):
        raise TypeError(f"expected a compiled net, got {type(net).__name__}")
    yield
    parts: dict[str, Any] = {}
    for piece in pieces[2:]:
        name, chunk = _load(piece, scopes)
        if isinstance(chunk, tuple):
            parts.setdefault(name, []).extend(chunk)
        else:
            parts.setdefault(name, {}).update(chunk)
        yield
    fields: dict[str, Any] = {}
    for name, joined in parts.items():
        empty = getattr(net, name)
        if isinstance(empty, tuple):
            fields[name] = tuple(joined)
        else:
            fields[name] = MappingProxyType(joined) if isinstance(empty, MappingProxyType) \
                else joined
        yield
    return dataclasses.replace(net, **fields)
