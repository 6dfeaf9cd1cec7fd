"""The recent past of a running program, in memory: bounded rings of scans and board samples.

Owns: what one program's history keeps (per scan sampled: scan number, publish time, state,
the number of forced symbols and the raw bits of every symbol; per status board sample: the
marking, the transitions' fire counts and the forces), the bounds (MAX_SCANS rows and
MAX_BYTES for both rings), and the window a client asks for, typed by core/present.py.
Does not know: clocks (times are arguments), threads, shared memory, HTTP.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from softplc.core.image import AddressError, ProcessImage, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.present import shown

MAX_SCANS: Final = 1000  # scans kept (docs/debug.md, the recent past)
MAX_BYTES: Final = 16 << 20  # both rings' arrays together: half for scans, half for the board
_STATES: Final = {int(s): s.name for s in PlcState}
I64 = npt.NDArray[np.int64]


@dataclass(frozen=True, slots=True)
class Layout:
    """One program's columns: its symbols (name, type, scale, image area and index), places
    and transitions, as the status board lists them."""

    program: str
    program_hash: str
    symbols: tuple[tuple[str, str, Any, str, int], ...]
    places: tuple[str, ...]
    transitions: tuple[str, ...]

    @classmethod
    def of_board(cls, doc: Mapping[str, Any]) -> Layout | None:
        """The layout of the program a board document shows; None without one."""
        if not doc.get("program_hash"):
            return None
        symbols = []
        for name, entry in (doc.get("symbols") or {}).items():
            if not isinstance(entry, dict):
                continue
            try:
                address = parse_address(str(entry.get("address")))
            except AddressError:
                continue
            symbols.append((str(name), str(entry.get("type")), entry.get("scale"),
                            address.attr, address.index))
        nodes = (doc.get("net") or {}).get("nodes") or {}  # absent: a net too large to draw
        return cls(str(doc.get("program") or ""), str(doc["program_hash"]), tuple(symbols),
                   tuple(str(p["name"]) for p in nodes.get("places") or ()),
                   tuple(str(t["name"]) for t in nodes.get("transitions") or ()))

    def gather(self) -> list[tuple[str, npt.NDArray[np.intp], npt.NDArray[np.intp]]]:
        """Per image area: the indexes to read and the columns they fill (one numpy take per
        area and sample, however many symbols)."""
        plan: dict[str, tuple[list[int], list[int]]] = {}
        for column, (_, _, _, attr, index) in enumerate(self.symbols):
            where, columns = plan.setdefault(attr, ([], []))
            where.append(index)
            columns.append(column)
        return [(attr, np.array(w, dtype=np.intp), np.array(c, dtype=np.intp))
                for attr, (w, c) in plan.items()]


def capacity(columns: int, max_scans: int, max_bytes: int) -> int:
    """Rows of `columns` int64 values (plus two) that fit: at most max_scans, at least 1."""
    return max(1, min(max_scans, max_bytes // (8 * (columns + 2))))


class _Ring:
    """Rows of int64 kept oldest first by a start index; appends overwrite the oldest."""

    def __init__(self, rows: int, columns: int) -> None:
        self.scans = np.zeros(rows, dtype=np.int64)
        self.t_ns = np.zeros(rows, dtype=np.int64)
        self.data = np.zeros((rows, columns), dtype=np.int64)
        self.start = self.count = 0

    @property
    def rows(self) -> int:
        return len(self.scans)

    @property
    def nbytes(self) -> int:
        return int(self.scans.nbytes + self.t_ns.nbytes + self.data.nbytes)

    def append(self, scan: int, t_ns: int) -> int:
        """The row to fill for a new sample (the oldest one's when full)."""
        if self.count < self.rows:
            row = (self.start + self.count) % self.rows
            self.count += 1
        else:
            row = self.start
            self.start = (self.start + 1) % self.rows
        self.scans[row], self.t_ns[row] = scan, t_ns
        return row

    def order(self) -> npt.NDArray[np.intp]:
        return (np.arange(self.count, dtype=np.intp) + self.start) % self.rows

    def last_scan(self) -> int | None:
        return int(self.scans[(self.start + self.count - 1) % self.rows]) if self.count else None


class History:
    """One program's recent past. add_scan and add_board come from the sampler's thread,
    window from request handlers: a lock keeps each whole."""

    def __init__(self, layout: Layout, max_scans: int = MAX_SCANS,
                 max_bytes: int = MAX_BYTES) -> None:
        self.layout = layout
        self._plan = layout.gather()
        # scans: state, forced count, then one column per symbol (its raw bits)
        self._scans = _Ring(capacity(len(layout.symbols) + 2, max_scans, max_bytes // 2),
                            len(layout.symbols) + 2)
        # board: the marking per place, then the fire counts per transition
        width = len(layout.places) + len(layout.transitions)
        self._board = _Ring(capacity(width, max_scans, max_bytes // 2), width)
        self._forced: list[dict[str, Any]] = [{}] * self._board.rows
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        return self._scans.nbytes + self._board.nbytes

    @property
    def max_rows(self) -> tuple[int, int]:
        """(scans, board samples) kept at most."""
        return self._scans.rows, self._board.rows

    def last_scan(self) -> int | None:
        return self._scans.last_scan()

    def add_scan(self, scan: int, t_ns: int, state: int, forced: int,
                 image: ProcessImage) -> None:
        with self._lock:
            row = self._scans.data[self._scans.append(scan, t_ns)]
            row[0], row[1] = state, forced
            for attr, where, columns in self._plan:
                area = getattr(image, attr)
                row[columns + 2] = area[where].astype(np.int64, copy=False)  # uint64: same bits

    def add_board(self, scan: int, t_ns: int, marking: Mapping[str, Any],
                  fired: Mapping[str, Any], forced: Mapping[str, Any]) -> None:
        layout = self.layout
        values = [int(marking.get(p, 0)) for p in layout.places]
        values += [int(fired.get(t, 0)) for t in layout.transitions]
        with self._lock:
            if self._board.last_scan() == scan:
                return
            row = self._board.append(scan, t_ns)
            self._board.data[row] = values
            previous = self._forced[(row - 1) % self._board.rows]
            self._forced[row] = previous if previous == forced else dict(forced)  # shared

    def window(self, since: int, symbols: Sequence[str], places: Sequence[str],
               wall_offset_ns: int) -> dict[str, Any]:
        """The samples after scan `since` (typed values of `symbols`, the marking of `places`),
        with the gaps between sampled scans. Times are Unix ms (monotonic + wall_offset_ns)."""
        with self._lock:
            s_order, b_order = self._scans.order(), self._board.order()
            scans, t_ns = self._scans.scans[s_order], self._scans.t_ns[s_order]
            data = self._scans.data[s_order]
            b_scans, b_t = self._board.scans[b_order], self._board.t_ns[b_order]
            b_data = self._board.data[b_order]
            b_forced = [self._forced[i] for i in b_order]
        keep = scans > since
        oldest = int(scans[0]) if len(scans) else None
        index = {name: i for i, (name, *_) in enumerate(self.layout.symbols)}
        rows = data[keep]
        values = {name: _typed(self.layout.symbols[index[name]], rows[:, index[name] + 2])
                  for name in symbols}
        chosen = scans[keep]
        return {
            "scans": chosen.tolist(), "t_ms": _ms(t_ns[keep], wall_offset_ns),
            "state": [_STATES.get(int(s), str(int(s))) for s in rows[:, 0]],
            "forced_count": rows[:, 1].tolist(), "values": values,
            "types": {name: self.layout.symbols[index[name]][1] for name in symbols},
            "gaps": gaps(chosen), "oldest_scan": oldest,
            "board": self._board_window(since, oldest, places, b_scans, b_t, b_data, b_forced,
                                        wall_offset_ns)}

    def _board_window(self, since: int, oldest: int | None, places: Sequence[str],
                      scans: I64, t_ns: I64, data: I64, forced: list[dict[str, Any]],
                      wall_offset_ns: int) -> dict[str, Any]:
        """Board samples after `since`, from the last one at or before the oldest scan kept
        (the marking the window starts with). `fired`: fire counts' increase since the
        previous sample, None for the first one kept or after a reset of the counts."""
        first = since + 1 if oldest is None else max(since + 1, oldest)
        before = np.nonzero(scans <= first)[0]
        start = int(before[-1]) if len(before) else 0
        keep = np.arange(len(scans)) >= start
        keep &= scans > since
        n_places = len(self.layout.places)
        column = {p: i for i, p in enumerate(self.layout.places)}
        counts = data[:, n_places:]
        fired: list[dict[str, int] | None] = []
        for i in np.nonzero(keep)[0]:
            delta = counts[i] - counts[i - 1] if i > 0 else None
            fired.append(None if delta is None or (delta < 0).any() else {
                self.layout.transitions[t]: int(delta[t]) for t in np.nonzero(delta)[0]})
        return {"scans": scans[keep].tolist(), "t_ms": _ms(t_ns[keep], wall_offset_ns),
                "marking": {p: data[keep, column[p]].tolist() for p in places},
                "fired": fired, "forced": [forced[i] for i in np.nonzero(keep)[0]]}


def gaps(scans: I64) -> list[list[int]]:
    """[first, last] of each run of scan numbers missing between consecutive samples."""
    if len(scans) < 2:
        return []
    jumps = np.nonzero(np.diff(scans) > 1)[0]
    return [[int(scans[j]) + 1, int(scans[j + 1]) - 1] for j in jumps]


def _ms(t_ns: I64, wall_offset_ns: int) -> list[float]:
    return [round((int(t) + wall_offset_ns) / 1e6, 3) for t in t_ns]


def _typed(symbol: tuple[str, str, Any, str, int], raw: I64) -> list[Any]:
    _, type_name, scale, _, _ = symbol
    if type_name == "bool":
        flags: list[Any] = (raw != 0).tolist()
        return flags
    bits = raw.astype(np.uint64)  # int64 storage of uint64 bits: back to unsigned
    return [shown(type_name, int(r), scale) for r in bits]
