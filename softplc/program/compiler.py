"""Validated spec -> CompiledNet: names, symbols, types, expressions, arrays.

Owns: every semantic check of a program (unknown names, arcs to missing places, actions that
write inputs, bool/word mismatches, guards that do not compile, coloured-arc rules), collected
with file:line before anything is built, and the build of the arrays and closures.
Does not know: devices, clocks, the scan.
"""

from __future__ import annotations

import hashlib
import re
from collections import ChainMap, defaultdict
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import numpy as np

from softplc.core.expr import Compiled, ExprError, NameKind, Scope, compile_expr, name_kind
from softplc.core.limits import DEFAULT, Limits
from softplc.core.net import (
    Action,
    ActionKind,
    CompiledNet,
    InputArc,
    OutputArc,
    Token,
    Transition,
)
from softplc.core.problems import Problem, ProgramError
from softplc.core.symbols import FIRST_SCAN, RETAIN_WORDS, Direction, IoImage, Retain, SymType
from softplc.core.values import MAX_FIELDS, field_name_problem
from softplc.program import compilelog
from softplc.program import fields as token_fields
from softplc.program.io_image import hashed_text, load_io_image, parse_io_image
from softplc.program.spec import parse_program, resolve
from softplc.program.specvalues import ArcSpec, ProgramSpec, TransitionSpec, Where
from softplc.program.suggest import did_you_mean
from softplc.program.teardown import bury
from softplc.program.typecheck import output_problem, real_to_integer

_UNKNOWN_NAME = re.compile(r"unknown name '([^']+)'")


@dataclass(frozen=True, slots=True)
class Summary:
    name: str
    places: int
    transitions: int
    arcs: int
    symbols: int
    subnets: int
    program_hash: str

    def __str__(self) -> str:
        return (f"program {self.name}: {self.places} places, {self.transitions} transitions, "
                f"{self.arcs} arcs, {self.symbols} symbols, {self.subnets} subnets "
                f"(hash {self.program_hash[:12]})")


def summarize(net: CompiledNet) -> Summary:
    arcs = sum(len(t.pre) + len(t.post) + len(t.test) + len(t.inhibit) for t in net.transitions)
    return Summary(net.name, len(net.place_names), len(net.transitions), arcs,
                   len(net.io.symbols), len(net.subnets), net.program_hash)


class _Compiler:
    def __init__(self, spec: ProgramSpec, io: IoImage, problems: list[Problem]) -> None:
        self.spec, self.io, self.problems = spec, io, problems
        self.places = {p.name: i for i, p in enumerate(spec.places)}
        self.events = {name for name, _ in spec.events}
        names: dict[str, NameKind] = {}
        for sym in io.symbols.values():
            # A scaled symbol reads as a real in engineering units (core/scaling.py).
            names[sym.name] = NameKind.REAL if sym.scaling else name_kind(sym.type)
        for ev in [*io.events, *self.events]:
            names[ev] = NameKind.EVENT
        names.setdefault(FIRST_SCAN, NameKind.EVENT)  # the system bit; a declared name wins
        self.names = names
        self.scope = Scope(names)  # shared by every expression that binds no token
        self.limits: Limits = DEFAULT.with_overrides({k: v for k, (v, _) in spec.limits.items()})

    def problem(self, where: Where, message: str, path: str | None = None) -> None:
        self.problems.append(Problem(where.file, where.line, path or where.path, message))

    def check_names(self) -> None:
        seen: dict[str, Where] = {}
        for kind, items in (("place", self.spec.places), ("transition", self.spec.transitions)):
            for item in items:
                if item.name in seen:
                    first = seen[item.name]
                    self.problem(item.where, f"{kind} name {item.name!r} is already used "
                                             f"({first.file}:{first.line})")
                seen[item.name] = item.where
        for name, where in self.spec.events:
            if name in self.io.symbols or name in self.io.events:
                self.problem(where, f"event {name!r} clashes with a symbol or io event")

    def expr(self, text: str, where: Where, tokens: set[str]) -> Compiled | None:
        # A view, not a copy of every symbol per expression: tokens shadow symbols.
        scope = Scope(ChainMap(dict.fromkeys(tokens, NameKind.TOKEN), self.names)) if tokens \
            else self.scope
        try:
            return compile_expr(text, scope)
        except ExprError as exc:
            unknown = _UNKNOWN_NAME.match(exc.message)
            hint = did_you_mean(unknown.group(1), [*self.names, *tokens]) if unknown else ""
            self.problem(where, f"{exc.message} in {text!r}{hint}")
            return None

    def writable(self, symbol: str, where: Where, want: SymType | None) -> bool:
        sym = self.io.symbols.get(symbol)
        if sym is None:
            self.problem(where, f"unknown symbol {symbol!r} (not in {self.io.path})"
                                f"{did_you_mean(symbol, self.io.symbols)}")
            return False
        if sym.direction is Direction.IN:
            self.problem(where, f"{symbol} is an input ({sym.address}); a program cannot write it")
            return False
        if want is not None and sym.type is not want:
            self.problem(where, f"{symbol} is a {sym.type.value}; expected a {want.value} here")
            return False
        return True

    def outputs(self, items: tuple[tuple[str, object, Where], ...]) -> tuple[tuple[str, int], ...]:
        out = []
        for symbol, value, where in items:
            if not self.writable(symbol, where, None):
                continue
            if (wrong := output_problem(self.io.symbols[symbol], value)) is not None:
                self.problem(where, wrong)
            else:
                out.append((symbol, int(value)))  # type: ignore[call-overload]
        return tuple(out)

    def action(self, text: str, where: Where, tokens: set[str]) -> Action | None:
        words = text.split(None, 1)
        if len(words) == 2 and words[0] in ("set", "reset", "pulse"):
            if self.writable(words[1], where, SymType.BOOL):
                return Action(ActionKind(words[0]), words[1])
            return None
        if len(words) == 2 and words[0] == "emit":
            if words[1] not in self.events:
                self.problem(where, f"event {words[1]!r} is not declared in the program's "
                                    f"events:{did_you_mean(words[1], self.events)}")
                return None
            return Action(ActionKind.EMIT, words[1])
        if "=" in text:
            target, _, value = text.partition("=")
            target = target.strip()
            if not self.writable(target, where, None):
                return None
            compiled = self.expr(value.strip(), where, tokens)
            if compiled and (wrong := real_to_integer(self.io.symbols[target], compiled)):
                self.problem(where, wrong)
            return None if compiled is None else Action(ActionKind.WRITE, target, compiled)
        self.problem(where, f"bad action {text!r}: "
                            "expected set X, reset X, pulse X, emit E or X = expr")
        return None

    def place_of(self, arc: ArcSpec) -> int | None:
        index = self.places.get(arc.place)
        if index is None:
            self.problem(arc.where, f"arc to unknown place {arc.place!r}"
                                    f"{did_you_mean(arc.place, self.places)}")
        elif arc.weight > self.limits.weight:
            self.problem(arc.where, f"arc weight {arc.weight:,} of {arc.place!r} exceeds the "
                                    f"limit {self.limits.weight:,} (limits.weight)")
        return index

    def transition(self, index: int, spec: TransitionSpec, coloured: list[bool]) -> Transition:
        tokens: set[str] = set()
        pre: list[InputArc] = []
        for arc in _merged(spec.pre):
            p = self.place_of(arc)
            if p is None:
                continue
            if arc.var is not None:
                if not coloured[p]:
                    self.problem(arc.where, f"var {arc.var!r}: place {arc.place} holds no records")
                elif arc.weight != 1:
                    self.problem(arc.where, "an arc that binds a variable has weight 1")
                tokens.add(arc.var)
            pre.append(InputArc(p, arc.weight, arc.var))
        post = [o for o in (self.output_arc(a, coloured, tokens) for a in _merged(spec.post)) if o]
        test = [(p, a.weight) for a in spec.test if (p := self.place_of(a)) is not None]
        inhibit = [(p, a.weight) for a in spec.inhibit if (p := self.place_of(a)) is not None]
        guard = None if spec.when is None else self.expr(spec.when[0], spec.when[1], tokens)
        actions = [a for a in (self.action(t, w, tokens) for t, w in spec.actions) if a]
        busy = self.outputs(spec.outputs)
        if busy and spec.duration_ns == 0:
            self.problem(spec.where,
                         "outputs: on a transition need a duration: (held while it runs)")
        if not pre and spec.duration_ns == 0 and spec.when is None:
            self.problem(spec.where,
                         "a transition with no input place and no guard fires every scan")
        touches = any(coloured[a.place] for a in pre) or any(coloured[o.place] for o in post)
        return Transition(spec.name, index, spec.priority, tuple(pre), tuple(post), tuple(test),
                          tuple(inhibit), guard, tuple(actions), spec.delay_ns, spec.duration_ns,
                          busy, touches, spec.where.line)

    def output_arc(self, arc: ArcSpec, coloured: list[bool], tokens: set[str]) -> OutputArc | None:
        p = self.place_of(arc)
        if p is None:
            return None
        if arc.token is None:
            return OutputArc(p, arc.weight)
        if not coloured[p]:
            self.problem(arc.where, f"token: place {arc.place} holds no records")
            return None
        if arc.weight > self.limits.coloured_place:  # each unit of weight is a record
            self.problem(arc.where, f"arc weight {arc.weight:,} to coloured place {arc.place!r} "
                                    f"exceeds the limit {self.limits.coloured_place:,} "
                                    "(limits.coloured_place)")
            return None
        if isinstance(arc.token, str):
            if arc.token not in tokens:
                self.problem(arc.where, f"token {arc.token!r} is not bound by an input arc")
                return None
            return OutputArc(p, arc.weight, var=arc.token)
        if len(arc.token) > MAX_FIELDS:
            self.problem(arc.where, f"a record of {len(arc.token)} fields (at most {MAX_FIELDS})")
        for name in arc.token:
            if (problem := field_name_problem(name)) is not None:
                self.problem(arc.where, problem)
        fields = {k: c for k, v in arc.token.items() if (c := self.expr(v, arc.where, tokens))}
        return OutputArc(p, arc.weight, fields=MappingProxyType(fields))


def _merged(arcs: tuple[ArcSpec, ...]) -> list[ArcSpec]:
    """`from: [p, p]` is one arc of weight 2: repeated plain arcs to a place add up."""
    out: list[ArcSpec] = []
    plain: dict[str, int] = {}
    for arc in arcs:
        if arc.var is None and arc.token is None and arc.place in plain:
            first = out[plain[arc.place]]
            out[plain[arc.place]] = ArcSpec(first.place, first.weight + arc.weight,
                                            where=first.where)
            continue
        if arc.var is None and arc.token is None:
            plain[arc.place] = len(out)
        out.append(arc)
    return out


def _build(spec: ProgramSpec, io: IoImage, c: _Compiler) -> CompiledNet:
    coloured = [p.coloured for p in spec.places]
    for p in spec.places:
        c.outputs(p.outputs)
        if p.capacity is not None and p.tokens > p.capacity:
            c.problem(p.where, f"initial tokens ({p.tokens}) exceed the capacity ({p.capacity})")
        if p.retain not in RETAIN_WORDS:
            c.problem(p.where, f"retain {p.retain!r}: expected none, retain or persistent",
                      f"{p.where.path}.retain")
    _initial_limits(spec, c)
    transitions = tuple(c.transition(i, t, coloured) for i, t in enumerate(spec.transitions))
    token_fields.check(spec, transitions, c.problem)  # `x.count` where tokens have `cnt`
    if c.problems:
        raise ProgramError(sorted(set(c.problems)))
    n_places = len(spec.places)
    touching: list[set[int]] = [set() for _ in range(n_places)]
    guard_deps, edge_deps = defaultdict[str, set[int]](set), defaultdict[str, set[int]](set)
    busy_drivers: dict[str, list[tuple[int, int]]] = defaultdict(list)
    bounded = [p.capacity is not None for p in spec.places]
    for t in transitions:
        for place in [a.place for a in t.pre] + [q for q, _ in t.test + t.inhibit]:
            touching[place].add(t.index)
        for o in t.post:
            if bounded[o.place]:
                touching[o.place].add(t.index)
        exprs = [t.guard] if t.guard else []
        for name in (n for e in exprs for n in e.reads):
            guard_deps[name].add(t.index)
        for name in (n for e in exprs for n in e.edges):
            edge_deps[name].add(t.index)
        for sym, value in t.busy_outputs:
            busy_drivers[sym].append((t.index, value))
    place_outputs = {i: c.outputs(p.outputs) for i, p in enumerate(spec.places) if p.outputs}
    moore: dict[str, list[tuple[int, int]]] = defaultdict(list)
    for i, outs in place_outputs.items():
        for sym, value in outs:
            moore[sym].append((i, value))
    initial_tokens: dict[int, tuple[Token, ...]] = {
        i: tuple(p.records or ()) for i, p in enumerate(spec.places) if p.coloured
    }
    digest = hashlib.sha256()
    for text in [*spec.texts, hashed_text(io)]:
        digest.update(text.encode())
    # Highest priority first; the sort is stable, so declaration order breaks ties.
    order = tuple(sorted(range(len(transitions)),
                         key=[-t.priority for t in transitions].__getitem__))
    capacity = np.array([-1 if p.capacity is None else p.capacity for p in spec.places], np.int64)
    return CompiledNet(
        spec.name, spec.file, digest.hexdigest(), io,
        tuple(p.name for p in spec.places), MappingProxyType(dict(c.places)),
        np.array([p.tokens for p in spec.places], np.int64), capacity,
        np.array(coloured, np.bool_), MappingProxyType(initial_tokens), transitions, order,
        MappingProxyType(place_outputs), _frozen(moore), _frozen(busy_drivers),
        tuple(tuple(sorted(s)) for s in touching), _frozen(guard_deps), _frozen(edge_deps),
        frozenset(c.events), tuple(spec.subnets), c.limits,
        place_where=tuple((p.where.file, p.where.line) for p in spec.places),
        transition_where=tuple((t.where.file, t.where.line) for t in spec.transitions),
        retain=tuple(Retain(p.retain) for p in spec.places),
        unconditioned=tuple(t.index for t in transitions if not t.pre and not t.test),
    )


def _initial_limits(spec: ProgramSpec, c: _Compiler) -> None:
    """The initial marking within the limits: a program that starts over them never runs."""
    lim = c.limits
    for p in spec.places:
        top, key = (lim.coloured_place, "coloured_place") if p.coloured else \
            (lim.place_tokens, "place_tokens")
        if p.tokens > top:
            c.problem(p.where, f"initial tokens ({p.tokens:,}) exceed the limit {top:,} "
                               f"(limits.{key})")
    where = spec.places[0].where if spec.places else None
    records = sum(p.tokens for p in spec.places if p.coloured)
    total = sum(p.tokens for p in spec.places)
    if where is not None and records > lim.coloured_total:
        c.problem(where, f"initial coloured tokens ({records:,}) exceed the limit "
                         f"{lim.coloured_total:,} (limits.coloured_total)")
    if where is not None and total > lim.total_tokens:
        c.problem(where, f"initial tokens ({total:,}) exceed the limit {lim.total_tokens:,} "
                         "(limits.total_tokens)")


def _frozen(d: dict[str, list[tuple[int, int]]] | dict[str, set[int]]) -> MappingProxyType:  # type: ignore[type-arg]
    return MappingProxyType({k: tuple(sorted(v)) for k, v in d.items()})


def _at_reference(problem: Problem, ref: str, where: Where) -> Problem:
    # A symbols file that cannot be read has no line of its own: the problem is the line
    # of the program that names it.
    if problem.line > 0:
        return problem
    return Problem(where.file, where.line, where.path, f"{ref!r}: {problem.message}")


def compile_text(text: str, filename: str, root: Path | None = None) -> CompiledNet:
    """Validate and compile a program given as text. Raises ProgramError listing every
    problem; nothing is built unless the whole program is valid."""
    compilelog.note(filename)
    spec, problems = parse_program(text, filename, root)
    io = None
    if spec.too_large or (spec.io_image is None and any("YAML" in p.message for p in problems)):
        raise ProgramError(sorted(set(problems)))
    if spec.io_image is None:
        if not any(p.path == "io_image" for p in problems):
            problems.append(Problem(filename, 1, "io_image",
                                    "missing io_image: (the symbols file)"))
    else:
        ref, where = spec.io_image
        target = resolve(Path(filename).parent, ref, root)
        if isinstance(target, str):
            problems.append(Problem(where.file, where.line, where.path, target))
        else:
            try:
                io = load_io_image(target)
            except ProgramError as exc:
                problems.extend(_at_reference(p, ref, where) for p in exc.problems)
    if io is None:
        raise ProgramError(sorted(set(problems)))
    return _compile_spec(spec, io, problems)


def _compile_spec(spec: ProgramSpec, io: IoImage, problems: list[Problem]) -> CompiledNet:
    compiler = _Compiler(spec, io, problems)
    compiler.check_names()
    net = _build(spec, io, compiler)
    box = [spec, compiler]  # the parsed program, let go of a piece at a time (teardown.py)
    del spec, compiler
    bury(box)
    return net


def compile_text_with_io(text: str, filename: str, io: IoImage,
                          root: Path | None = None) -> CompiledNet:
    """Compile a program against an io image given by the caller (a PNML import, whose
    symbols come from beside the net, or none at all). Raises ProgramError like compile_text."""
    spec, problems = parse_program(text, filename, root)
    if spec.too_large or any("YAML" in p.message for p in problems):
        raise ProgramError(sorted(set(problems)))
    return _compile_spec(spec, io, problems)


def compile_file(path: str | Path, root: Path | None = None) -> CompiledNet:
    if str(path).partition("#")[0].lower().endswith(".xml"):  # an SFC chart: docs/sfc.md
        from softplc.sfc.load import load_chart
        c = load_chart(path)
        return c.compiled(lambda: compile_text_with_io(c.program_text, c.file,
                                                       parse_io_image(c.io_text, c.file), root))
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProgramError(
            [Problem(str(path), 0, "", f"cannot read program: {exc.strerror}")]) from None
    return compile_text(text, str(path), root)
