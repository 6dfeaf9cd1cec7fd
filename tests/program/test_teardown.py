"""program/teardown.py: a compile's big temporaries are let go a container at a time, and
nothing anybody else still holds is touched."""

from __future__ import annotations

import gc
import weakref

from softplc.program.teardown import bury
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
        bury(box)
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
    bury(box)
    assert kept == {"tokens": 42, "name": "p42"} and kept.lines == {"tokens": 42}
    assert len(kept_places) == 100 and kept_places[99]["name"] == "p99"


def test_where_no_scan_thread_waits_a_burial_frees_all_at_once() -> None:
    """The compile process (runtime/compileproc.py) turns the piecewise burial off: the same
    result, without walking the tree (there, freeing in one cascade delays nobody)."""
    from softplc.program import teardown

    gc.disable()
    teardown.piecewise(False)
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
        teardown.piecewise(True)
        gc.enable()
