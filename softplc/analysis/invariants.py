"""Place and transition invariants by Farkas' algorithm, in exact integers.

Owns: the minimal semi-positive invariants of an incidence matrix (y >= 0, y^T C = 0 for
places; x >= 0, C x = 0 for transitions) and what they imply (conservative, structurally
bounded places). Does not know: markings, exploration, files.

Python ints throughout: coefficients never overflow. Farkas' algorithm can blow up; past
MAX_ROWS intermediate rows it stops and says so (`complete` False).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import gcd

import numpy as np
import numpy.typing as npt

MAX_ROWS = 20_000
# Farkas keeps dense rows of (columns + unknowns) integers in Python lists: beyond this many
# matrix cells it is not started (a 10,000-place ring took 4.8 GB before this bound), and the
# result says "not complete". Controller nets and the benchmark models are far below it.
MAX_CELLS = 250_000


@dataclass(frozen=True, slots=True)
class Invariants:
    vectors: tuple[tuple[int, ...], ...]  # minimal-support semi-positive invariants
    complete: bool  # False: Farkas stopped at MAX_ROWS

    @property
    def support(self) -> frozenset[int]:
        return frozenset(i for v in self.vectors for i, x in enumerate(v) if x)


def _normal(row: list[int]) -> list[int]:
    g = 0
    for x in row:
        g = gcd(g, x)
    return [x // g for x in row] if g > 1 else row


def farkas(matrix: npt.NDArray[np.int64]) -> Invariants:
    """Minimal semi-positive y with y^T matrix = 0 (rows of `matrix` are the unknowns)."""
    n, m = matrix.shape
    if n * m > MAX_CELLS:
        return Invariants((), False)
    # Each row: (the remaining columns of y^T matrix, y itself).
    rows: list[tuple[list[int], list[int]]] = [
        ([int(x) for x in matrix[i]], [1 if j == i else 0 for j in range(n)]) for i in range(n)]
    complete = True
    for col in range(m):
        keep = [r for r in rows if r[0][col] == 0]
        pos = [r for r in rows if r[0][col] > 0]
        neg = [r for r in rows if r[0][col] < 0]
        for a, av in pos:
            for b, bv in neg:
                ka, kb = -b[col], a[col]
                new = _normal([ka * x + kb * y for x, y in zip(a + av, b + bv, strict=True)])
                keep.append((new[:m], new[m:]))
            if len(keep) > MAX_ROWS:
                complete = False
                break
        rows = _minimal(keep)
        if not complete:
            break
    vectors = sorted({tuple(v) for c, v in rows if complete or not any(c)})
    return Invariants(tuple(v for v in vectors if any(v)), complete)


def _minimal(rows: list[tuple[list[int], list[int]]]) -> list[tuple[list[int], list[int]]]:
    """Drop rows whose support strictly contains another row's support (not minimal) and
    duplicates: keeps Farkas' intermediate sets small."""
    seen: set[tuple[int, ...]] = set()
    unique: list[tuple[list[int], list[int]]] = []
    for c, v in rows:
        key = tuple(v)
        if key not in seen and any(v):
            seen.add(key)
            unique.append((c, v))
    supports = [frozenset(i for i, x in enumerate(v) if x) for _, v in unique]
    out = []
    for i, s in enumerate(supports):
        if not any(supports[j] < s for j in range(len(supports)) if j != i):
            out.append(unique[i])
    return out


def p_invariants(pre: npt.NDArray[np.int64], post: npt.NDArray[np.int64]) -> Invariants:
    """P-invariants: y^T C = 0 with C = (post - pre)^T, places as rows."""
    return farkas((post - pre).T)


def t_invariants(pre: npt.NDArray[np.int64], post: npt.NDArray[np.int64]) -> Invariants:
    """T-invariants: C x = 0, transitions as rows."""
    return farkas(post - pre)
