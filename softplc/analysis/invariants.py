"""Place and transition invariants by Farkas' algorithm, bounded in work and memory.

Owns: semi-positive invariants of an incidence matrix (y >= 0, y^T C = 0 for places; x >= 0,
C x = 0 for transitions) by Farkas' algorithm on int64 numpy rows, with the minimal-support
test of Martinez and Silva (a combination of rows a and b is kept only if no other row's
support lies inside supp(a) | supp(b)), the column with the fewest new rows next, and
budgets; what they imply (conservative, structurally bounded places) is analyze.py's.
Does not know: markings, exploration, files.

Why budgets: the minimal invariants can be exponentially many (a ring of n fork-join
stages of width w has w**n); the old unbounded version never finished on a 253-place
benchmark net. Past a budget the result says `complete` False and why; the vectors it
has are still invariants (every row keeps y^T C = c, and a row is returned only when c is
0), perhaps not all the minimal ones: bounds derived from them stay sound.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

# Rows kept between two columns; past it the rows with the smallest supports are kept
# (a beam: fewer invariants, each still one).
MAX_ROWS = 2_000
# int64 cells of the new rows built for one column (32 MB); past it the pairs with the
# smallest supports are combined first.
MAX_NEW_CELLS = 4_000_000
# Cells touched in the whole run (combinations, support tests, column choices): ~1 s of
# numpy here; the 253-place fork-join net of tests/analysis/test_budget.py spends it.
MAX_WORK = 100_000_000
# Matrices above this many cells are not started (a 10,000-place ring took 4.8 GB before
# any bound); the result says "not complete".
MAX_CELLS = 250_000
_SAFE = 1 << 62  # |coefficients| below this: a combination cannot wrap an int64


@dataclass(frozen=True, slots=True)
class Invariants:
    vectors: tuple[tuple[int, ...], ...]  # semi-positive invariants (minimal when complete)
    complete: bool  # False: a budget ran out (`why`); the vectors are invariants still
    why: str = ""

    @property
    def support(self) -> frozenset[int]:
        return frozenset(i for v in self.vectors for i, x in enumerate(v) if x)


@dataclass(slots=True)
class _Run:
    """Farkas' rows and what the run has spent."""

    rows: npt.NDArray[np.int64]  # each row: the remaining columns of y^T C, then y
    m: int  # columns of C
    work: int = 0
    why: str = ""  # the budget that stopped the run
    beam: bool = False  # some rows or pairs were left out: fewer invariants, each still one

    def support(self, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
        return np.asarray(rows[:, self.m:] != 0, dtype=np.float32)

    def stop(self, why: str) -> None:
        self.why = self.why or why


def farkas(matrix: npt.NDArray[np.int64], max_work: int = MAX_WORK) -> Invariants:
    """Semi-positive y with y^T matrix = 0 (rows of `matrix` are the unknowns)."""
    n, m = matrix.shape
    if n * m > MAX_CELLS:
        return Invariants((), False, f"not computed: {n} x {m} matrix over {MAX_CELLS:,} "
                                     "cells")
    run = _Run(np.hstack([matrix.astype(np.int64), np.eye(n, dtype=np.int64)]), m)
    todo = [c for c in range(m) if matrix[:, c].any()]
    while todo and not run.why:
        run.work += run.rows.shape[0] * (len(todo) + n)
        col = _next_column(run.rows, todo)
        todo.remove(col)
        _eliminate(run, col, max_work)
    rows = run.rows
    done = rows[~rows[:, :m].any(axis=1)][:, m:]
    vectors = sorted({tuple(int(x) for x in v) for v in done if v.any()})
    why = run.why or (f"more than {MAX_ROWS:,} intermediate rows: the smallest supports "
                      "kept" if run.beam else "")
    return Invariants(tuple(vectors), not why, why)


def _next_column(rows: npt.NDArray[np.int64], todo: list[int]) -> int:
    """The column whose elimination adds the fewest rows (pos * neg - pos - neg)."""
    part = rows[:, todo]
    pos, neg = (part > 0).sum(axis=0), (part < 0).sum(axis=0)
    return todo[int(np.argmin(pos * neg - pos - neg))]


def _eliminate(run: _Run, col: int, max_work: int) -> None:
    rows = run.rows
    c = rows[:, col]
    keep, pos, neg = rows[c == 0], rows[c > 0], rows[c < 0]
    pairs = _pairs(run, pos, neg)
    if len(pairs[0]) == 0:
        run.rows = keep
        return
    a, b = pos[pairs[0]], neg[pairs[1]]
    if int(np.abs(a).max()) * int(np.abs(b[:, col]).max()) + \
            int(np.abs(b).max()) * int(np.abs(a[:, col]).max()) >= _SAFE:
        run.stop("coefficients past int64")
        return
    run.work += a.size * 2
    union = run.support(a) + run.support(b) > 0
    old = run.support(rows)
    run.work += union.shape[0] * union.shape[1] * old.shape[0]
    if run.work > max_work:
        run.stop(f"work budget of {max_work:,} operations spent")
        return
    # Rows of the old set whose support lies in the union: a and b themselves, and any
    # other one proves the combination not minimal.
    outside = (~union).astype(np.float32) @ old.T
    minimal = (outside == 0).sum(axis=1) == 2
    new = a[minimal] * -b[minimal, col:col + 1] + b[minimal] * a[minimal, col:col + 1]
    gcd = np.gcd.reduce(new, axis=1)
    new //= np.maximum(gcd, 1)[:, None]
    # No new row equals an old one (that one's support would lie in the union), and equal
    # new rows are rare: only the new ones are made unique.
    run.rows = _beam(run, np.vstack([keep, np.unique(new, axis=0)]))


def _pairs(run: _Run, pos: npt.NDArray[np.int64],
           neg: npt.NDArray[np.int64]) -> tuple[npt.NDArray[np.intp], npt.NDArray[np.intp]]:
    """Every (pos, neg) pair, or the ones with the smallest supports that fit MAX_NEW_CELLS."""
    i = np.repeat(np.arange(len(pos)), len(neg))
    j = np.tile(np.arange(len(neg)), len(pos))
    width = max(1, pos.shape[1])
    if len(i) * width <= MAX_NEW_CELLS:
        return i, j
    run.beam = True
    size = run.support(pos).sum(axis=1)[i] + run.support(neg).sum(axis=1)[j]
    order = np.sort(np.argsort(size, kind="stable")[:MAX_NEW_CELLS // width])
    return i[order], j[order]


def _beam(run: _Run, rows: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """At most MAX_ROWS rows: the finished ones (c all 0) first, then the smallest supports."""
    if len(rows) <= MAX_ROWS:
        return rows
    run.beam = True
    finished = ~rows[:, :run.m].any(axis=1)
    size = (rows[:, run.m:] != 0).sum(axis=1) + np.where(finished, 0, rows.shape[1])
    return rows[np.sort(np.argsort(size, kind="stable")[:MAX_ROWS])]


def p_invariants(pre: npt.NDArray[np.int64], post: npt.NDArray[np.int64]) -> Invariants:
    """P-invariants: y^T C = 0 with C = (post - pre)^T, places as rows."""
    return farkas((post - pre).T)


def t_invariants(pre: npt.NDArray[np.int64], post: npt.NDArray[np.int64]) -> Invariants:
    """T-invariants: C x = 0, transitions as rows."""
    return farkas(post - pre)
