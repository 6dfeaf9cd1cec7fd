"""Program text -> flat spec: parse the YAML shape, expand subnets, substitute parameters.

Owns: the program file format (places, transitions, arcs, subnets, params, events), read
into the spec values of specvalues.py, each with its file and line. Problems are collected,
not raised; past a size limit (sizes.py) the expansion stops where it went over.
Does not know: symbols' meaning, expressions' meaning (compiler.py checks those).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from softplc.core import limits
from softplc.core.expr import ExprError, Value, substitute
from softplc.core.problems import Problem
from softplc.core.values import record_problems
from softplc.program.iectime import BAD_DURATION, duration_ns
from softplc.program.sizes import DEFAULT_SIZES, SizeExceeded, SizeLimits, Sizes
from softplc.program.specvalues import ArcSpec, PlaceSpec, ProgramSpec, TransitionSpec, Where
from softplc.program.suggest import did_you_mean, did_you_mean_key
from softplc.program.teardown import bury
from softplc.program.yamlload import YList, YMap, line_of, load_yaml, trap_hint

TOP_KEYS = {"program", "net", "description", "io_image", "params", "places", "transitions",
            "subnets", "events", "limits"}
PLACE_KEYS = {"tokens", "capacity", "outputs", "coloured", "description", "retain"}
TRANSITION_KEYS = {"from", "to", "read", "inhibit", "priority", "when", "do", "delay",
                   "duration", "outputs", "description"}
MAX_SUBNET_DEPTH = 4


class _Parser:
    """Parses one file (the program, or a subnet instance with its prefix and parameters)."""

    def __init__(self, spec: ProgramSpec, problems: list[Problem], file: str, prefix: str,
                 params: dict[str, Value], root: Path | None, depth: int,
                 sizes: Sizes) -> None:
        self.spec, self.problems, self.file = spec, problems, file
        self.prefix, self.params, self.root, self.depth = prefix, params, root, depth
        self.sizes = sizes  # shared by every instance: the expanded program's size

    def count(self, key: str, n: int, where: Where) -> None:  # SizeExceeded past a limit
        self.sizes.add(key, n, where.file, where.line, where.path)

    def problem(self, line: int, path: str, message: str) -> None:
        self.problems.append(Problem(self.file, line, path, message))

    def where(self, container: Any, key: Any, path: str) -> Where:
        return Where(self.file, line_of(container, key), path)

    def name(self, local: str) -> str:
        """A place name as written in this file: a parameter, else prefixed with the instance."""
        if local in self.params:
            return str(self.params[local])
        return self.prefix + local

    def symbol(self, text: str) -> str:
        return str(self.params.get(text, text))

    def expr(self, text: str, where: Where) -> str:
        if not self.params:
            return text
        try:
            return substitute(text, self.params)
        except ExprError:
            return text  # the compiler reports the syntax error with its location

    def check_keys(self, data: YMap, allowed: set[str], path: str) -> None:
        for key in data:
            if key not in allowed:
                self.problem(line_of(data, key), f"{path}.{key}".lstrip("."),
                             f"unknown key {key!r}{did_you_mean_key(key, allowed)}; "
                             f"expected one of {', '.join(sorted(allowed))}")

    def parse(self, data: Any, top: bool) -> None:
        if not isinstance(data, YMap):
            self.problem(getattr(data, "line", 1), "",
                         "expected a mapping with places: and transitions:")
            return
        self.check_keys(data, TOP_KEYS, "")
        if top:
            self.spec.name = str(data.get("program", data.get("net", Path(self.file).stem)))
            if "io_image" in data:
                self.io_image(data)
        if "limits" in data:
            self.limits(data, top)
        for name, line in self.named(data, "events"):
            self.spec.events.append((self.prefix + name, Where(self.file, line, f"events.{name}")))
        places = data.get("places", YMap())
        if isinstance(places, YMap):
            for pname, pdata in places.items():
                self.place(str(pname), pdata, self.where(places, pname, f"places.{pname}"))
        else:
            self.problem(line_of(data, "places"), "places", "expected a mapping of place: {...}")
        subnets = data.get("subnets", YMap())
        if isinstance(subnets, YMap):
            for iname, idata in subnets.items():
                self.subnet(str(iname), idata, self.where(subnets, iname, f"subnets.{iname}"))
        transitions = data.get("transitions", YMap())
        if isinstance(transitions, YMap):
            for tname, tdata in transitions.items():
                self.transition(str(tname), tdata,
                                self.where(transitions, tname, f"transitions.{tname}"))
        else:
            self.problem(line_of(data, "transitions"), "transitions",
                         "expected a mapping of transition: {...}")

    def io_image(self, data: YMap) -> None:
        ref, where = data["io_image"], self.where(data, "io_image", "io_image")
        if not isinstance(ref, str) or not ref.strip():
            # str() of a mapping or list would name a file that cannot exist
            self.problem(where.line, "io_image",
                         f"expected the file name of a symbols file, not {repr(ref)[:40]}")
            return
        self.spec.io_image = (ref, where)

    def limits(self, data: YMap, top: bool) -> None:
        raw, line = data["limits"], line_of(data, "limits")
        if not top:
            self.problem(line, "limits", "limits: belongs in the main program, not in a subnet")
            return
        if not isinstance(raw, YMap):
            self.problem(line, "limits", "expected a mapping of limit: whole number")
            return
        for key, value in raw.items():
            where = self.where(raw, key, f"limits.{key}")
            problem = limits.override_problem(key, value)
            if problem is not None:
                self.problem(where.line, where.path, f"{problem}{trap_hint(value)}")
            else:
                self.spec.limits[str(key)] = (value, where)

    def named(self, data: YMap, key: str) -> list[tuple[str, int]]:
        value = data.get(key, YList())
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            self.problem(line_of(data, key), key, "expected a list of names")
            return []
        return [(v, line_of(value, i)) for i, v in enumerate(value)]

    # -- places -----------------------------------------------------------------------------

    def place(self, name: str, data: Any, where: Where) -> None:
        data = YMap() if data is None else data
        if not isinstance(data, YMap):
            self.problem(where.line, where.path,
                         "expected {tokens: N, capacity: N, outputs: [...]}")
            return
        self.check_keys(data, PLACE_KEYS, where.path)
        tokens, records = 0, None
        raw = data.get("tokens", 0)
        if isinstance(raw, list):
            if self.records_ok(raw, f"{where.path}.tokens"):
                records = tuple(dict(r) for r in raw)
                tokens = len(records)
        elif isinstance(raw, int) and not isinstance(raw, bool) and raw >= 0:
            tokens = raw
        else:
            self.problem(line_of(data, "tokens"), f"{where.path}.tokens",
                         f"tokens must be a whole number >= 0 or a list of records{trap_hint(raw)}")
        coloured = records is not None or data.get("coloured") is True
        if coloured and records is None and tokens:
            self.problem(line_of(data, "tokens"), f"{where.path}.tokens",
                         "a coloured place starts with a list of records, not a count")
        capacity = data.get("capacity")
        if capacity is not None and (not isinstance(capacity, int) or isinstance(capacity, bool)
                                     or capacity < 1):
            self.problem(line_of(data, "capacity"), f"{where.path}.capacity",
                         "capacity must be a whole number >= 1")
            capacity = None
        outputs = self.outputs(data, where)
        self.count("places", 1, where)
        self.spec.places.append(PlaceSpec(self.prefix + name, tokens,
                                          records if coloured else None, coloured,
                                          capacity, outputs, where, data.get("retain", "retain")))
        self.spec.place_names.add(self.prefix + name)

    def records_ok(self, raw: list[Any], path: str) -> bool:
        """Every record of a coloured place's `tokens:` carries only values the runtime can
        carry (core/values.py); each problem at the line of its record or field."""
        ok = True
        for i, record in enumerate(raw):
            for name, message in record_problems(record):
                line = line_of(record, name) if isinstance(record, YMap) and name is not None \
                    else line_of(raw, i)
                self.problem(line, f"{path}[{i}]" + ("" if name is None else f".{name}"),
                             message + ("; coloured tokens are records, e.g. [{id: 1}]"
                                        if name is None and not isinstance(record, dict) else ""))
                ok = False
        return ok

    def outputs(self, data: YMap, where: Where) -> tuple[tuple[str, Value, Where], ...]:
        raw = data.get("outputs")
        path = f"{where.path}.outputs"
        if raw is None:
            return ()
        if isinstance(raw, list):
            return tuple((self.symbol(str(s)), 1, self.where(raw, i, path))
                         for i, s in enumerate(raw))
        if isinstance(raw, YMap):
            return tuple((self.symbol(str(s)), v, self.where(raw, s, path)) for s, v in raw.items())
        self.problem(line_of(data, "outputs"), path,
                     "expected a list of symbols or {symbol: value}")
        return ()

    # -- transitions ------------------------------------------------------------------------

    def transition(self, name: str, data: Any, where: Where) -> None:
        if not isinstance(data, YMap):
            self.problem(where.line, where.path, "expected {from: [...], to: [...], when: ...}")
            return
        self.check_keys(data, TRANSITION_KEYS, where.path)
        priority = data.get("priority", 0)
        if not isinstance(priority, int) or isinstance(priority, bool):
            self.problem(line_of(data, "priority"), f"{where.path}.priority",
                         "priority must be a whole number (higher fires first)")
            priority = 0
        when = None
        if "when" in data:
            text = data["when"]
            w = self.where(data, "when", f"{where.path}.when")
            if isinstance(text, str) and text.strip().lower() in ("on", "off", "yes", "no"):
                self.problem(w.line, w.path, f"guard {text!r}{trap_hint(text)}")
                text = "false"  # reported: not also as an unknown name (one problem a mistake)
            self.count("expression_chars", len(str(text)), w)  # before it is parsed
            when = (self.expr(str(text).lower() if isinstance(text, bool) else str(text), w), w)
        actions = []
        raw_do = data.get("do", YList())
        if not isinstance(raw_do, list):
            self.problem(line_of(data, "do"), f"{where.path}.do", "expected a list of actions")
            raw_do = YList()
        for i, act in enumerate(raw_do):
            w = self.where(raw_do, i, f"{where.path}.do[{i}]")
            self.count("expression_chars", len(str(act)), w)  # before it is parsed
            actions.append((self.action(str(act)), w))
        pre, post, test, inhibit = (self.arcs(data, key, where)
                                    for key in ("from", "to", "read", "inhibit"))
        self.count("transitions", 1, where)
        self.count("arcs", len(pre) + len(post) + len(test) + len(inhibit), where)
        self.count("expression_chars", sum(len(str(a.token or "")) for a in post), where)
        self.spec.transitions.append(TransitionSpec(
            self.prefix + name, pre, post, test, inhibit, priority, when, tuple(actions),
            self.duration(data, "delay", where), self.duration(data, "duration", where),
            self.outputs(data, where), where))

    def action(self, text: str) -> str:
        words = text.split(None, 1)
        if len(words) == 2 and words[0] in ("set", "reset", "pulse", "emit"):
            target = words[1].strip()
            if words[0] == "emit":
                event = self.prefix + target if target not in self.params else self.symbol(target)
                return f"emit {event}"
            return f"{words[0]} {self.symbol(target)}"
        if "=" in text:
            target, _, value = text.partition("=")
            target = target.rstrip(":").strip()
            return f"{self.symbol(target)} = {self.expr(value.strip(), Where(self.file, 0, ''))}"
        return text

    def duration(self, data: YMap, key: str, where: Where) -> int:
        raw = data.get(key, 0)  # none: 0
        try:
            return duration_ns(raw)
        except ValueError as exc:
            self.problem(line_of(data, key), f"{where.path}.{key}", str(exc))
            return BAD_DURATION  # reported: not also "outputs need a duration" (one problem)

    def arcs(self, data: YMap, key: str, where: Where) -> tuple[ArcSpec, ...]:
        raw = data.get(key)
        path = f"{where.path}.{key}"
        if raw is None:
            return ()
        items: list[tuple[Any, Where]]
        if isinstance(raw, YMap):
            items = [(YMap({p: w}), self.where(raw, p, path)) for p, w in raw.items()]
        elif isinstance(raw, list):
            items = [(item, self.where(raw, i, path)) for i, item in enumerate(raw)]
        elif isinstance(raw, str):
            items = [(raw, self.where(data, key, path))]
        else:
            self.problem(line_of(data, key), path, "expected a list of places")
            return ()
        arcs = [self.arc(item, w) for item, w in items]
        return tuple(a for a in arcs if a is not None)

    def arc(self, item: Any, where: Where) -> ArcSpec | None:
        if isinstance(item, str):
            return ArcSpec(self.name(item), 1, where=where)
        if isinstance(item, dict) and "place" in item:
            weight = item.get("weight", 1)
            token = item.get("token")
            if isinstance(token, dict):
                token = {str(k): self.expr(str(v), where) for k, v in token.items()}
            elif token is not None:
                token = str(token)
            return self._weighted(str(item["place"]), weight, where, item.get("var"), token)
        if isinstance(item, dict) and len(item) == 1:
            ((place, weight),) = item.items()
            return self._weighted(str(place), weight, where, None, None)
        self.problem(where.line, where.path,
                     "an arc is a place name, {place: weight}, or {place: p, weight: n, var: v}")
        return None

    def _weighted(self, place: str, weight: Any, where: Where, var: Any,
                  token: str | dict[str, str] | None) -> ArcSpec | None:
        if not isinstance(weight, int) or isinstance(weight, bool) or weight < 1:
            self.problem(where.line, where.path,
                         f"arc weight of {place!r} must be a whole number >= 1")
            return None
        return ArcSpec(self.name(place), weight, None if var is None else str(var), token, where)

    # -- subnets ----------------------------------------------------------------------------

    def subnet(self, instance: str, data: Any, where: Where) -> None:
        if not isinstance(data, YMap) or "net" not in data:
            self.problem(where.line, where.path, "expected {net: FILE, with: {param: value}}")
            return
        if self.depth >= MAX_SUBNET_DEPTH:
            self.problem(where.line, where.path, f"subnets nest deeper than {MAX_SUBNET_DEPTH}")
            return
        target = resolve(Path(self.file).parent, str(data["net"]), self.root)
        if isinstance(target, str):
            self.problem(line_of(data, "net"), f"{where.path}.net", target)
            return
        self.count("subnets", 1, where)
        try:
            text = target.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            self.problem(line_of(data, "net"), f"{where.path}.net", f"cannot read subnet "
                         f"{data['net']!r}: {getattr(exc, 'strerror', '') or 'not UTF-8 text'}")
            return
        self.count("text_chars", len(text), where)
        given = data.get("with", YMap())
        sub, problems = load_yaml(text, str(target))
        self.problems.extend(problems)
        if not isinstance(sub, YMap) or not isinstance(given, dict):
            self.problem(where.line, where.path, "subnet file or its `with:` is not a mapping")
            return
        declared = sub.get("params", [])
        declared = [str(p) for p in declared] if isinstance(declared, list) else []
        for missing in sorted(set(declared) - set(given)):
            self.problem(where.line, where.path,
                         f"subnet {data['net']} needs parameter {missing!r}")
        for extra in sorted(set(given) - set(declared)):
            self.problem(line_of(given, extra), f"{where.path}.with.{extra}",
                         f"subnet {data['net']} has no parameter {extra!r}"
                         f"{did_you_mean(extra, declared)} "
                         f"(it takes: {', '.join(declared) or 'none'})")
        params = {str(k): v if isinstance(v, int | float) else self.resolve_param(str(v))
                  for k, v in given.items()}
        self.spec.subnets.append(self.prefix + instance)
        self.spec.texts.append(text)
        _Parser(self.spec, self.problems, str(target), f"{self.prefix}{instance}.", params,
                self.root, self.depth + 1, self.sizes).parse(sub, top=False)

    def resolve_param(self, value: str) -> str:
        """A parameter value names a symbol, or a place of the instantiating net (prefixed)."""
        if value in self.params:
            return str(self.params[value])
        if self.prefix + value in self.spec.place_names:
            return self.prefix + value
        return value


def resolve(base: Path, ref: str, root: Path | None) -> Path | str:
    """A referenced file, relative to the referring file (and so named); with `root`, inside it."""
    if "\0" in ref:  # the OS refuses such names: a located problem, never a ValueError
        return f"file name {ref!r} contains a NUL character"
    path = Path(ref)
    if root is not None and path.is_absolute():
        return f"absolute path {ref!r} is not allowed here"
    full = (base / path).resolve()
    if root is not None and not full.is_relative_to(root.resolve()):
        return f"path {ref!r} leaves the program directory"
    shown = Path(os.path.normpath(base / path))  # named as the program is: relative or not
    return shown if shown.resolve() == full else full


def parse_program(text: str, filename: str, root: Path | None = None,
                  limits: SizeLimits = DEFAULT_SIZES) -> tuple[ProgramSpec, list[Problem]]:
    """The flat spec and every problem; past a size limit (sizes.py) it stops, spec empty."""
    sizes = Sizes(limits)
    spec = ProgramSpec(Path(filename).stem, filename, None, texts=[text])
    data, problems = None, list[Problem]()
    try:
        sizes.add("text_chars", len(text), filename, 1, "")  # before it is parsed
        data, problems = load_yaml(text, filename)
        if data is not None:
            _Parser(spec, problems, filename, "", {}, root, 0, sizes).parse(data, top=True)
        elif not problems:
            problems.append(Problem(filename, 1, "", "empty program"))
    except SizeExceeded as exc:
        problems.append(exc.problem)
        spec.places, spec.transitions, spec.too_large = [], [], True
    box = [data]  # the YAML document, let go of a piece at a time (teardown.py)
    del data
    bury(box)
    return spec, problems
