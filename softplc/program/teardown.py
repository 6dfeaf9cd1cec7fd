"""Big temporaries freed a container at a time, between scans.

Owns: `burying`, the steps that take the last references to trees of containers (a replaced
net and its engine) and let them go one container per step, roots first; `bury`, the same at
once.
Why: freeing a tree in one go is a single decref cascade that no other thread can interrupt;
a replaced 10,000-transition net took milliseconds to free, a scan waiting at 1 ms, so the
scan thread frees it in steps between its scans (runtime/download.py). Each container held
here is freed when its slot is cleared: its children are still held further on, so nothing
cascades. Objects also referenced from elsewhere are simply not freed: nothing is ever
modified. A compile's own temporaries (the YAML document, the parsed program) are freed at
once (`bury`): compiles run in the compile process, `check`, `simulate` and `analyze`, where
no scan thread shares the interpreter (the piecewise switch that once served a compile beside
the scan is gone, issue 40.7).
Does not know: what the objects mean.
"""

from __future__ import annotations

import gc
from types import MappingProxyType
from typing import Any

from softplc.core.steps import Steps

_LEAVES = (str, bytes, int, float, bool, type(None))


_CHUNK = 64  # containers freed per step (a program object with its attributes: ~1-4 µs)
_SLOTS = 20_000  # ... or containers of this many references in all
_SIZED = (dict, list, tuple, set, frozenset)
_FORGET = 1024  # seen ids dropped per step
_TRIM = 16384  # emptied slots of the walk's list given back per step
_SHARDS = 64
_WALK_STEP = 256  # objects looked at per step of the walk (~0.3-1 µs each)


def bury(box: list[Any]) -> None:
    """Empty `box` and let go of what it held, at once. The caller hands over its last
    references in the box (a reference passed as an argument would stay on the caller's
    stack until the call returns, and the cascade would come then)."""
    box.clear()


def burying(box: list[Any]) -> Steps[None]:
    """A container at a time (core/steps.py; the sizes above): the scan thread frees a
    replaced net between its scans (runtime/download.py)."""
    order: list[Any] = []
    # Ids seen, in shards: one set of ~100,000 ids took 3 ms to grow and 4 ms to free.
    seen: list[set[int]] = [set() for _ in range(_SHARDS)]
    while box:
        yield from _walk(box.pop(), order, seen)
    while seen:
        shard = seen.pop()  # emptied, then its table freed (64 at once: ~0.3 ms)
        while shard:
            _forget(shard)
            yield
        del shard
    start = 0
    while start < len(order):
        start = _release(order, start)
        yield
    while order:  # the emptied list itself (~300,000 slots for 10,000 transitions)
        del order[-_TRIM:]
        yield


def _walk(root: Any, order: list[Any], seen: list[set[int]]) -> Steps[None]:
    """Append `root` and every container and program object under it not yet seen to
    `order`, parents before children."""
    key = id(root)
    if key in seen[(key >> 4) % _SHARDS]:
        return  # already under another root: released with it
    seen[(key >> 4) % _SHARDS].add(key)
    i = len(order)
    order.append(root)
    work = 0
    while i < len(order):
        children = _children(order[i])
        i += 1
        work += 1
        # The leaves of a big container are held here too, each freed in its own chunk: a
        # dict of 10,000 names freed 0.6 ms of strings and ints with it in one go.
        big = len(children) > _CHUNK
        for start in range(0, len(children), _WALK_STEP):
            for child in children[start:start + _WALK_STEP]:
                if isinstance(child, _LEAVES):
                    if big:
                        order.append(child)
                else:
                    key = id(child)
                    shard = seen[(key >> 4) % _SHARDS]
                    if key not in shard:
                        shard.add(key)
                        order.append(child)
            work += min(_WALK_STEP, len(children) - start)
            if work >= _WALK_STEP:  # a step: about this many objects looked at
                work = 0
                yield
        if work >= _WALK_STEP:  # a run of objects without children counts too
            work = 0
            yield


def _forget(seen: set[int]) -> None:
    for _ in range(min(_FORGET, len(seen))):
        seen.pop()


def _release(order: list[Any], start: int) -> int:
    """Free containers from `start` on until _CHUNK of them, or containers of _SLOTS
    references in all, are let go (each reference let go costs ~5 ns: a container of 10,000
    ~50 µs); where the next step starts."""
    i, stop, slots = start, min(start + _CHUNK, len(order)), 0
    while i < stop and slots < _SLOTS:
        held = order[i]
        slots += len(held) + 1 if isinstance(held, _SIZED) else 1
        del held
        order[i] = None  # one container's own memory: its children are still in `order`
        i += 1
    return i


def _children(obj: Any) -> list[Any]:
    if isinstance(obj, dict):
        return [*obj.keys(), *obj.values(), *getattr(obj, "__dict__", {}).values()]
    if isinstance(obj, MappingProxyType):
        return gc.get_referents(obj)  # the mapping it shows
    if isinstance(obj, list | tuple | set | frozenset):
        return [*obj, *getattr(obj, "__dict__", {}).values()]
    if type(obj).__module__.startswith("softplc."):  # the program's own values
        values = list(getattr(obj, "__dict__", {}).values())
        for cls in type(obj).__mro__:
            for name in getattr(cls, "__slots__", ()):
                if hasattr(obj, name):
                    values.append(getattr(obj, name))
        return values
    return []  # functions, types, modules, numpy arrays ...: not ours to walk into
