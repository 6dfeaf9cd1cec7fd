"""The flat spec of a program: the values the parser (spec.py) yields and the compiler reads.

Owns: Where (file, line, path of every item), the arc, place and transition specs, and
ProgramSpec, the whole program with its subnets expanded and parameters substituted.
Does not know: YAML, how the values are parsed or checked.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from softplc.core.expr import Value


@dataclass(frozen=True, slots=True)
class Where:
    file: str
    line: int
    path: str


@dataclass(frozen=True, slots=True)
class ArcSpec:
    place: str
    weight: int
    var: str | None = None
    token: str | dict[str, str] | None = None  # output arcs: pass var through, or fields
    where: Where = Where("", 0, "")


@dataclass(frozen=True, slots=True)
class PlaceSpec:
    name: str
    tokens: int
    records: tuple[dict[str, Value], ...] | None  # coloured initial tokens
    coloured: bool
    capacity: int | None
    outputs: tuple[tuple[str, Value, Where], ...]
    where: Where
    retain: object = "retain"  # as written; the compiler checks it (none, retain, persistent)


@dataclass(frozen=True, slots=True)
class TransitionSpec:
    name: str
    pre: tuple[ArcSpec, ...]
    post: tuple[ArcSpec, ...]
    test: tuple[ArcSpec, ...]
    inhibit: tuple[ArcSpec, ...]
    priority: int
    when: tuple[str, Where] | None
    actions: tuple[tuple[str, Where], ...]
    delay_ns: int
    duration_ns: int
    outputs: tuple[tuple[str, Value, Where], ...]
    where: Where


@dataclass(slots=True)
class ProgramSpec:
    name: str
    file: str
    io_image: tuple[str, Where] | None
    places: list[PlaceSpec] = field(default_factory=list)
    transitions: list[TransitionSpec] = field(default_factory=list)
    events: list[tuple[str, Where]] = field(default_factory=list)
    subnets: list[str] = field(default_factory=list)
    texts: list[str] = field(default_factory=list)  # every file's text, for the program hash
    place_names: set[str] = field(default_factory=set)  # of `places`, for lookups
    limits: dict[str, tuple[int, Where]] = field(default_factory=dict)  # `limits:` overrides
    too_large: bool = False  # the expansion stopped at a size limit (sizes.py): build nothing
