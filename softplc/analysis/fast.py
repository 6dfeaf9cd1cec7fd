"""Vectorised breadth-first reachability graph of a bounded P/T net (interleaving semantics).

Owns: the numpy exploration used when every place has a known bound (P-invariants or
capacities): a whole BFS level at a time, enabledness of every transition for every frontier
marking at once, markings packed into 64-bit keys (per-place bit widths from the bounds) and a
sorted array of seen keys. Does not know: guards, timing, scan steps, files.

Memory per stored state: the marking (one byte per place while bounds < 256), its key
(8 bytes per 64 bits of packed marking), parent index (4) and incoming transition (2).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from softplc.analysis.graph import MAX_REPORTED, Conflict, Deadlock, Graph
from softplc.analysis.model import AnalysisNet, IntArray

KeyArray = npt.NDArray[np.generic]


class _Packer:
    """Marking rows -> sortable keys (uint64, or fixed-width bytes past 64 bits)."""

    def __init__(self, bounds: IntArray) -> None:
        widths = [max(1, int(b).bit_length()) for b in bounds]
        self.words: list[list[tuple[int, int]]] = [[]]  # per word: (place, shift)
        used = 0
        for p, w in enumerate(widths):
            if used + w > 64:
                self.words.append([])
                used = 0
            self.words[-1].append((p, used))
            used += w
        self.n_words = len(self.words)

    def deltas(self, change: npt.NDArray[np.int32]) -> npt.NDArray[np.uint64]:
        """Per transition, what firing it adds to a one-word key (mod 2^64)."""
        out = np.zeros(len(change), np.uint64)
        for p, shift in self.words[0]:
            out += (change[:, p].astype(np.int64) << shift).astype(np.uint64)
        return out

    def keys(self, rows: npt.NDArray[np.integer[Any]]) -> KeyArray:
        out = np.zeros((len(rows), self.n_words), np.uint64)
        for k, word in enumerate(self.words):
            acc = out[:, k]
            for p, shift in word:
                acc |= rows[:, p].astype(np.uint64) << np.uint64(shift)
        if self.n_words == 1:
            return out[:, 0]
        return np.ascontiguousarray(out).view(np.dtype((np.void, 8 * self.n_words))).ravel()


def explore_fast(net: AnalysisNet, bounds: IntArray, max_states: int) -> Graph:
    """Full BFS. `bounds`: an upper bound per place valid for every reachable marking."""
    P, T = net.n_places, net.n_transitions
    g = Graph("interleaving", bounds=[0] * P, fired=[False] * T)
    pack = _Packer(bounds)
    store = np.uint8 if int(bounds.max(initial=0)) < 256 else np.int32
    change = (net.post - net.pre).astype(np.int32)
    arcs = _arc_tables(net)
    frontier = net.initial.astype(np.int32)[None, :]
    fkeys = pack.keys(frontier)
    seen = fkeys.copy()
    # One-word keys are linear in the marking (fields never overflow: every count stays within
    # its bound), so a successor's key is its source's key plus the transition's key delta:
    # the successor markings of a level are only built for the new states.
    dkeys = pack.deltas(change) if pack.n_words == 1 else None
    levels: list[npt.NDArray[np.generic]] = [frontier.astype(store)]
    parents: list[npt.NDArray[np.int32]] = [np.array([-1], np.int32)]
    vias: list[npt.NDArray[np.int16]] = [np.array([-1], np.int16)]
    total, base = 1, 0
    dead_rows: list[int] = []
    ever = np.zeros(T, np.bool_)
    bmax = frontier.max(axis=0)
    mmax = int(frontier.sum())
    while len(frontier):
        enabled = _enabled(frontier, arcs, T)
        counts = enabled.sum(axis=1)
        g.edges += int(counts.sum())
        ever |= enabled.any(axis=0)
        dead_rows.extend((base + np.flatnonzero(counts == 0)).tolist())
        _conflicts(net, frontier, base, g, levels, parents, vias)
        src, via = np.nonzero(enabled)
        keys: KeyArray
        if dkeys is not None:
            keys = fkeys[src].astype(np.uint64) + dkeys[via]
        else:
            keys = pack.keys(frontier[src] + change[via])
        keys, first = np.unique(keys, return_index=True)
        pos: npt.NDArray[np.intp] = np.searchsorted(seen, keys)
        hit: npt.NDArray[np.bool_] = pos < len(seen)
        hit[hit] = seen[pos[hit]] == keys[hit]
        new = ~hit
        if not new.any():
            break
        room = max_states - total
        keep = np.flatnonzero(new)
        if len(keep) > room:
            keep = keep[:room]
            g.complete = False
        pick = first[keep]
        frontier = frontier[src[pick]] + change[via[pick]]
        fkeys = keys[keep]
        seen = np.insert(seen, pos[keep], fkeys)
        base_next = total
        levels.append(frontier.astype(store))
        parents.append((base + src[pick]).astype(np.int32))
        vias.append(via[pick].astype(np.int16))
        bmax = np.maximum(bmax, frontier.max(axis=0))
        mmax = max(mmax, int(frontier.sum(axis=1).max()))
        base, total = base_next, total + len(pick)
        if not g.complete:
            dead_rows.extend(_dead_in(frontier, arcs, T, base))
            break
    g.states = total
    g.bounds = [int(b) for b in bmax]
    g.max_marking = mmax
    g.fired = [bool(e) for e in ever]
    g.deadlock_count = len(dead_rows)
    for row in dead_rows[:MAX_REPORTED]:
        marking = _row(levels, row)
        g.deadlocks.append(Deadlock(
            {net.place_names[p]: int(n) for p, n in enumerate(marking) if n},
            _path(net, parents, vias, row)))
    key_bytes = 8 * pack.n_words
    g.bytes_per_state = float(np.dtype(store).itemsize * P + key_bytes + 4 + 2)
    return g


def _arc_tables(net: AnalysisNet) -> list[list[tuple[npt.NDArray[np.intp], IntArray, str]]]:
    """Per transition: (places, thresholds, kind) for its pre/test (>=), inhibitor (<) and
    capacity (m - pre + post <= cap) conditions."""
    tables = []
    need = np.maximum(net.pre, net.test)
    for t in range(net.n_transitions):
        conds = []
        ps = np.flatnonzero(need[t])
        if len(ps):
            conds.append((ps, need[t, ps], "ge"))
        ps = np.flatnonzero(net.inhibit[t])
        if len(ps):
            conds.append((ps, net.inhibit[t, ps], "lt"))
        ps = np.flatnonzero((net.capacity >= 0) & (net.post[t] > 0))
        if len(ps):
            limit = net.capacity[ps] + net.pre[t, ps] - net.post[t, ps]
            conds.append((ps, limit, "le"))
        tables.append(conds)
    return tables


def _enabled(rows: npt.NDArray[np.int32], arcs: list[list[tuple[npt.NDArray[np.intp], IntArray,
             str]]], T: int) -> npt.NDArray[np.bool_]:
    out = np.ones((len(rows), T), np.bool_)
    for t, conds in enumerate(arcs):
        col = out[:, t]
        for ps, th, kind in conds:
            sub = rows[:, ps]
            if kind == "ge":
                col &= (sub >= th).all(axis=1)
            elif kind == "lt":
                col &= (sub < th).all(axis=1)
            else:
                col &= (sub <= th).all(axis=1)
    return out


def _dead_in(rows: npt.NDArray[np.int32], arcs: list[list[tuple[npt.NDArray[np.intp], IntArray,
             str]]], T: int, base: int) -> list[int]:
    return (base + np.flatnonzero(~_enabled(rows, arcs, T).any(axis=1))).tolist()


def _row(levels: list[npt.NDArray[np.generic]], index: int) -> npt.NDArray[np.generic]:
    for level in levels:
        if index < len(level):
            row: npt.NDArray[np.generic] = level[index]
            return row
        index -= len(level)
    raise IndexError(index)


def _path(net: AnalysisNet, parents: list[npt.NDArray[np.int32]],
          vias: list[npt.NDArray[np.int16]], index: int) -> tuple[str, ...]:
    flat_parent = np.concatenate(parents)
    flat_via = np.concatenate(vias)
    steps = []
    while index > 0:
        steps.append(net.transition_names[int(flat_via[index])])
        index = int(flat_parent[index])
    return tuple(reversed(steps))


def _conflicts(net: AnalysisNet, rows: npt.NDArray[np.int32], base: int, g: Graph,
               levels: list[npt.NDArray[np.generic]], parents: list[npt.NDArray[np.int32]],
               vias: list[npt.NDArray[np.int16]]) -> None:
    """Place-driven outputs with two different values in one marking (vectorised per pair
    of drivers); transitions whose own actions disagree are found once, structurally."""
    if not net.moore:
        return
    drivers: dict[str, list[tuple[int, int]]] = {}
    for p, outs in net.moore.items():
        for sym, v in outs:
            drivers.setdefault(sym, []).append((p, v))
    reported = {c.symbol for c in g.conflicts}
    for sym, ds in sorted(drivers.items()):
        if sym in reported:
            continue
        for i, (p1, v1) in enumerate(ds):
            hit = next(((p2, v2) for p2, v2 in ds[i + 1:] if v2 != v1
                        and ((rows[:, p1] > 0) & (rows[:, p2] > 0)).any()), None)
            if hit is None:
                continue
            p2, v2 = hit
            row = int(np.flatnonzero((rows[:, p1] > 0) & (rows[:, p2] > 0))[0])
            g.conflicts.append(Conflict(
                sym, (f"place {net.place_names[p1]} = {v1}", f"place {net.place_names[p2]} = {v2}"),
                (net.where_place(p1), net.where_place(p2)),
                _path(net, parents, vias, base + row)))
            break
