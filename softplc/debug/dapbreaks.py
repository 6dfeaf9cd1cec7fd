"""The breakpoints one debug adapter session set on the PLC (debug/dap.py): a line of the
program's YAML -> the transitions of its block -> one PLC breakpoint each (a subnet's line:
one per instance), and function breakpoints `fire:T`, `enabled:T`, `when:EXPR` (or just T).

Owns: which PLC breakpoints stand for which DAP breakpoint, the DAP answers (verified, or
not with the reason), removing them again (per source, per kind, all at the end).
Does not know: the wire, the pause, how the PLC checks a breakpoint (it refuses bad ones).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Final

from softplc.api.client import ApiClient, ApiError, ApiUnreachable
from softplc.debug.dapsource import LineMap

KINDS: Final = ("fire", "enabled", "when")
VERB: Final = {"fire": "fires", "enabled": "becomes enabled", "when": "becomes true"}
LIST_WAIT_S: Final = 5.0
Answer = dict[str, Any]


@dataclass(frozen=True, slots=True)
class Point:
    """One DAP breakpoint and the PLC breakpoints it stands for."""

    id: int
    plc_ids: tuple[int, ...]


class BreakBook:
    """`lines` None: no program given, so no line maps to a transition. `base`: the first
    line's number as the editor counts (1 by default, or 0)."""

    def __init__(self, client: ApiClient) -> None:
        self.client = client
        self.lines: LineMap | None = None
        self.program = ""  # the program's name, for messages
        self.base = 1
        self._sources: dict[str, list[Point]] = {}
        self._functions: list[Point] = []
        self._next_id = 1

    def set_source(self, path: str, wanted: Iterable[dict[str, Any]]) -> list[Answer]:
        """Replace the breakpoints of `path` (DAP's setBreakpoints) with `wanted`."""
        key = os.path.realpath(path) if path else ""
        self._drop(self._sources.pop(key, []))
        points, answers = [], []
        for asked in wanted:
            line = int(asked.get("line", 0)) + 1 - self.base
            point, answer = self._line_point(path, line, str(asked.get("mode") or "fire"))
            answers.append(answer)
            if point is not None:
                points.append(point)
        self._sources[key] = points
        return answers

    def set_functions(self, wanted: Iterable[dict[str, Any]]) -> list[Answer]:
        self._drop(self._functions)
        self._functions, answers = [], []
        for asked in wanted:
            name = str(asked.get("name", "")).strip()
            kind, sep, target = name.partition(":")
            on, target = (kind.strip(), target.strip()) if sep and kind.strip() in KINDS \
                else ("fire", name)
            point, answer = self._add([(on, target)])
            answers.append(answer)
            if point is not None:
                self._functions.append(point)
        return answers

    def clear(self) -> None:
        points = self._points()
        self._sources, self._functions = {}, []
        self._drop(points)

    def dap_ids(self, plc_ids: Iterable[object]) -> list[int]:
        """The DAP breakpoints among which PLC breakpoints `plc_ids` are."""
        hit = set(plc_ids)
        return [p.id for p in self._points() if hit & set(p.plc_ids)]

    def _points(self) -> list[Point]:
        return [p for ps in self._sources.values() for p in ps] + self._functions

    def _line_point(self, path: str, line: int, mode: str) -> tuple[Point | None, Answer]:
        if self.lines is None:
            return None, _unverified("no program: attach with \"program\": the program's YAML "
                                     "path to set breakpoints on its lines")
        block = self.lines.at(path, line)
        if block is None:
            starts = self.lines.starts(path)
            where = (f"transitions start at lines {', '.join(map(str, starts))}" if starts
                     else f"{os.path.basename(path)} defines no transition of {self.program}")
            return None, _unverified(f"no transition at line {line}: {where}")
        on = mode if mode in ("fire", "enabled") else "fire"
        point, answer = self._add([(on, name) for name in block.names])
        return point, {**answer, "line": block.first - 1 + self.base}

    def _add(self, targets: list[tuple[str, str]]) -> tuple[Point | None, Answer]:
        ids: list[int] = []
        try:
            for on, target in targets:
                self.client.add_breakpoint(on, target)
                ids.append(self._new_id(on, target))
        except (ApiError, LookupError) as exc:
            self._drop([Point(0, tuple(ids))])
            return None, _unverified(exc.message if isinstance(exc, ApiError) else str(exc))
        point = Point(self._next_id, tuple(ids))
        self._next_id += 1
        said = " and ".join(f"{target} {VERB[on]}" for on, target in targets)
        return point, {"id": point.id, "verified": True, "message": said}

    def _new_id(self, on: str, target: str) -> int:
        """The id the PLC gave the breakpoint just added: the reply's `id` is the command's,
        so it is the newest one on the PLC's list (the status board's, refreshed about every
        50 ms) with this kind and target that no point of this session holds."""
        held = {i for point in self._points() for i in point.plc_ids}
        deadline = time.monotonic() + LIST_WAIT_S
        while True:
            ids = [int(p["id"]) for p in self.client.breakpoints().get("breakpoints") or []
                   if (p.get("on"), p.get("target")) == (on, target) and p.get("id") not in held]
            if ids:
                return max(ids)
            if time.monotonic() > deadline:
                raise LookupError(f"{target} {VERB[on]}: set, but not on the PLC's list "
                                  f"within {LIST_WAIT_S:.0f} s")
            time.sleep(0.05)

    def _drop(self, points: list[Point]) -> None:
        for plc_id in (i for point in points for i in point.plc_ids):
            # gone already (`softplc break clear`), or the PLC is: nothing left to remove
            with contextlib.suppress(ApiError, ApiUnreachable):
                self.client.remove_breakpoint(plc_id)


def _unverified(message: str) -> Answer:
    return {"verified": False, "message": message}
