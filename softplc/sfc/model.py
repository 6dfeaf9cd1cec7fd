"""A chart read from PLCopen XML, in the chart's own terms, before it becomes a net.

Owns: the values the reader produces and the translation consumes (Variable, Step,
Transition, Action, Chart), each with the XML line it came from.
Does not know: XML, YAML, the engine.
"""

from __future__ import annotations

from dataclasses import dataclass, field

# IEC elementary types -> (softplc symbol type, the ST kind the translation checks with).
# TIME is kept in a DINT as milliseconds (CODESYS's TIME is a 32-bit count of ms too).
IEC_TYPES: dict[str, tuple[str, str]] = {
    "BOOL": ("bool", "bool"), "INT": ("int", "int"), "UINT": ("word", "int"),
    "WORD": ("word", "int"), "DINT": ("dint", "int"), "UDINT": ("udint", "int"),
    "DWORD": ("udint", "int"), "REAL": ("real", "real"), "LREAL": ("lreal", "real"),
    "TIME": ("dint", "time"),
}


@dataclass(frozen=True, slots=True)
class Variable:
    name: str
    iec: str  # the IEC type as declared (BOOL, INT, TIME, or a derived type's name)
    address: str | None  # located: %IX0.0 ...; None: memory
    section: str  # inputVars, outputVars, localVars, globalVars ...
    init: str | None
    line: int

    @property
    def kind(self) -> str:
        return IEC_TYPES[self.iec][1] if self.iec in IEC_TYPES else f"fb:{self.iec.upper()}"


@dataclass(frozen=True, slots=True)
class Step:
    name: str
    line: int
    initial: bool
    x: float = 0.0  # drawing position (<position>), kept by the export
    y: float = 0.0


@dataclass(slots=True)
class Transition:
    name: str
    line: int
    sources: tuple[str, ...]
    targets: tuple[str, ...]
    condition: str  # the ST text as written (for comments and the export)
    guard: str = ""  # softplc expression; "" = always true
    reads: tuple[str, ...] = ()  # steps whose .X the condition requires
    inhibits: tuple[str, ...] = ()  # steps whose NOT .X the condition requires
    delay_ms: int | None = None  # `Step.T >= T#d` as the whole condition
    rank: int = 0  # 0 = first in its selection divergence (leftmost or lowest priority)
    never: bool = False  # the condition is the constant FALSE
    xy: tuple[float, float] | None = None  # drawing position (<position>), for the export


@dataclass(frozen=True, slots=True)
class Action:
    step: str
    qualifier: str
    name: str  # the action's or the BOOL variable's name
    line: int
    target: str | None  # a BOOL variable driven by the action
    statements: tuple[tuple[str, str], ...] = ()  # (variable, softplc expression)
    duration: str = ""  # as written (L, D, DS)
    duration_ms: int = 0


@dataclass(slots=True)
class Chart:
    file: str
    pou: str
    pou_line: int
    steps: list[Step] = field(default_factory=list)
    transitions: list[Transition] = field(default_factory=list)
    actions: list[Action] = field(default_factory=list)
    variables: dict[str, Variable] = field(default_factory=dict)  # upper-case name -> var

    def step_line(self, name: str) -> int:
        return next((s.line for s in self.steps if s.name == name), self.pou_line)
