"""program/teardown.py: a replaced net's big containers are let go a container at a time, and
nothing anybody else still holds is touched."""

from __future__ import annotations

import gc
import weakref
from typing import ClassVar

from softplc.core.steps import drain
from softplc.program.teardown import bury, burying
from softplc.program.yamlref import YList, YMap


def document(n: int) -> YMap:
    root = YMap()
    root.lines = {}
    places = YList()
    places.lines = []
    for i in range(n):
        place = YMap({"tokens": i, "name": f"p{i}"})
        place.lines = {"tokens": i}
        places.append(place)
    root["places"] = places
    root["alias"] = places[0]  # shared within the tree, as a YAML alias makes it
    return root


def test_everything_buried_is_freed_and_the_box_is_emptied() -> None:
    gc.disable()  # freed by reference counting alone, as in a compile
    try:
        root = document(1000)
        watched = [weakref.ref(root), weakref.ref(root["places"]),
                   *(weakref.ref(p) for p in root["places"][::97])]
        box = [root]
        del root
        drain(burying(box))
        assert box == []
        assert [w() for w in watched] == [None] * len(watched)
    finally:
        gc.enable()


def test_what_others_still_hold_is_kept_whole() -> None:
    root = document(100)
    kept = root["places"][42]
    kept_places = root["places"]
    box = [root]
    del root
    drain(burying(box))
    assert kept == {"tokens": 42, "name": "p42"} and kept.lines == {"tokens": 42}
    assert len(kept_places) == 100 and kept_places[99]["name"] == "p99"


def test_a_compiles_burial_frees_all_at_once() -> None:
    """bury (a compile's temporaries: the compile process, check, simulate, analyze): the
    same result as burying, without walking the tree (there, freeing in one cascade delays
    nobody)."""
    from softplc.program import teardown

    gc.disable()
    try:
        root = document(1000)
        watched = [weakref.ref(root), weakref.ref(root["places"])]
        walked: list[object] = []
        original, teardown._walk = teardown._walk, lambda *a: walked.append(a)  # type: ignore[assignment]
        box = [root]
        del root
        bury(box)
        assert box == [] and walked == []  # nothing walked: freed as the box let go
        assert [w() for w in watched] == [None, None]
    finally:
        teardown._walk = original
        gc.enable()



class Leaf(int):
    """A leaf the walk does not look into (an int) that says when it is freed."""

    freed: ClassVar[list[int]] = []

    def __del__(self) -> None:
        Leaf.freed.append(int(self))


def test_no_step_frees_a_big_container_with_all_its_leaves() -> None:
    """A container of thousands of leaves (a net's names, its index dicts) is not freed with
    all of them in one step: they are held and let go a chunk at a time."""
    from softplc.program import teardown

    gc.disable()
    try:
        Leaf.freed.clear()
        box: list[object] = [[[Leaf(1000 * k + i) for i in range(1000)] for k in range(20)]]
        per_step = []
        for _ in teardown.burying(box):
            per_step.append(len(Leaf.freed))
            Leaf.freed.clear()
        per_step.append(len(Leaf.freed))
        assert box == [] and sum(per_step) == 20_000  # every leaf freed, each once
        assert max(per_step) <= teardown._CHUNK
    finally:
        gc.enable()


def test_a_run_of_objects_without_children_is_walked_in_steps() -> None:
    """Empty containers (or leaves held for a big container) give the walk nothing to loop
    over; they still count, so that a step ends after _WALK_STEP of them."""
    from softplc.program import teardown

    looked: list[int] = [0]
    original = teardown._children

    def counting(obj: object) -> list[object]:
        looked[0] += 1
        return original(obj)

    teardown._children = counting  # type: ignore[assignment]
    try:
        box: list[object] = [[[] for _ in range(20_000)]]
        per_step = []
        for _ in teardown.burying(box):
            per_step.append(looked[0])
            looked[0] = 0
        assert max(per_step) <= teardown._WALK_STEP + 1
    finally:
        teardown._children = original
