"""Where a program's transitions are written: the debug adapter's map from a line of a YAML
file to the transitions whose block holds it (debug/dap.py).

Owns: a transition's block (its key line and the lines under it, indented deeper, up to the
next line indented as little as the key; trailing blank lines left out), one file's lines to
transition names (a subnet's file: one name per instance), and back.
Does not know: DAP, HTTP, the PLC.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from softplc.core.net import CompiledNet


@dataclass(frozen=True, slots=True)
class Block:
    """The lines `first..last` (1-based, inclusive) of `path` that define `names`."""

    path: str  # resolved, as os.path.realpath gives it
    first: int
    last: int
    names: tuple[str, ...]  # the transition, or each instance's of a subnet's transition


class LineMap:
    """The transitions of one compiled program by file and line."""

    def __init__(self, blocks: list[Block], program: str) -> None:
        self.blocks = blocks
        self.program = program  # the program file, resolved
        self._where = {name: block for block in blocks for name in block.names}

    @classmethod
    def of(cls, net: CompiledNet, program: Path | str) -> LineMap:
        """`net` compiled from `program`; its transitions' (file, line) as the compiler
        recorded them, relative paths taken from the program's directory when not found."""
        by_key: dict[tuple[str, int], list[str]] = {}
        for t, (file, line) in zip(net.transitions, net.transition_where, strict=True):
            by_key.setdefault((_resolve(file, program), line), []).append(t.name)
        texts: dict[str, list[str]] = {}
        blocks = []
        for (path, line), names in sorted(by_key.items()):
            if path not in texts:
                texts[path] = _lines(path)
            last = block_end(texts[path], line)
            blocks.append(Block(path, line, last, tuple(names)))
        return cls(blocks, os.path.realpath(program))

    def at(self, path: str, line: int) -> Block | None:
        """The block of `path` (any spelling of it) that holds `line` (1-based)."""
        real = os.path.realpath(path)
        for block in self.blocks:
            if block.path == real and block.first <= line <= block.last:
                return block
        return None

    def where(self, transition: str) -> Block | None:
        return self._where.get(transition)

    def starts(self, path: str) -> list[int]:
        """The key lines of the transitions written in `path`, for a message."""
        real = os.path.realpath(path)
        return [block.first for block in self.blocks if block.path == real]


def block_end(lines: list[str], first: int) -> int:
    """The last line (1-based) of the YAML mapping entry whose key is on line `first`."""
    if not 1 <= first <= len(lines):
        return first
    indent = _indent(lines[first - 1])
    last = first
    for number in range(first + 1, len(lines) + 1):
        text = lines[number - 1]
        if not text.strip():
            continue
        if _indent(text) <= indent:
            break
        last = number
    return last


def _indent(text: str) -> int:
    return len(text) - len(text.lstrip(" "))


def _resolve(file: str, program: Path | str) -> str:
    if not os.path.isabs(file) and not os.path.exists(file):
        file = os.path.join(os.path.dirname(program), file)
    return os.path.realpath(file)


def _lines(path: str) -> list[str]:
    try:
        return Path(path).read_text(encoding="utf-8").splitlines()
    except OSError:
        return []
