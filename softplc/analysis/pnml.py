"""PNML (ISO/IEC 15909-2, `ptnet` type) import; export lives in pnml_export.py, whose
functions callers also import from here.

Owns: reading PNML (pages, reference places and transitions) into a bare P/T AnalysisNet,
or, with softplc's data (in toolspecific, or a `NET.softplc.json` mapping beside the file),
into a CompiledNet through the program compiler; `structure`, what a round trip must keep.
Every problem is located (file:line).
Does not know: how PNML is written, exploration, the CLI.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from softplc.analysis.model import AnalysisNet, check_size, from_pt
from softplc.analysis.pnml_export import PTNET, TOOL
from softplc.analysis.pnml_export import export_compiled as export_compiled
from softplc.analysis.pnml_export import export_pt as export_pt
from softplc.analysis.xmltree import Node, parse_xml
from softplc.core.net import CompiledNet
from softplc.core.problems import Problem, ProgramError
from softplc.program.compiler import compile_text_with_io
from softplc.program.io_image import load_io_image
from softplc.program.sizes import count_problem

# -- import -------------------------------------------------------------------------------

@dataclass(slots=True)
class _Item:
    ident: str
    name: str
    line: int
    node: Node


@dataclass(slots=True)
class PnmlNet:
    """A parsed PNML net: places, transitions and arcs with their lines."""

    file: str
    name: str
    places: list[_Item]
    initial: list[int]
    transitions: list[_Item]
    arcs: list[tuple[int, int, int, bool, Node]]  # (place, transition, weight, to_place, node)
    tool: dict[str, Any] | None  # the net's softplc toolspecific data


class _Reader:
    def __init__(self, file: str) -> None:
        self.file = file
        self.problems: list[Problem] = []

    def problem(self, node: Node, message: str) -> None:
        self.problems.append(Problem(self.file, node.line, node.tag, message))

    def tool_json(self, node: Node, tag: str) -> dict[str, Any] | None:
        for ts in node.all("toolspecific"):
            if ts.attrs.get("tool") != TOOL:
                continue
            inner = ts.child(tag)
            if inner is None:
                continue
            try:
                value = json.loads(inner.text)
            except json.JSONDecodeError as exc:
                self.problem(inner, f"toolspecific {tag}: bad JSON ({exc.msg})")
                return None
            if not isinstance(value, dict):
                self.problem(inner, f"toolspecific {tag}: expected a JSON object")
                return None
            return value
        return None

    def count(self, node: Node, path: tuple[str, ...], default: int, what: str) -> int:
        text = node.text_of(*path)
        if text is None or text == "":
            return default
        if not text.isdigit():
            self.problem(node.child(path[0]) or node, f"{what} {text!r}: expected a whole "
                         "number >= 0" + ("" if what == "initial marking" else " (> 0)"))
            return default
        return int(text)


def _elements(page: Node) -> Iterator[Node]:
    """The page's elements in document order, nested pages flattened (iteratively: pages
    may nest as deep as xmltree.MAX_DEPTH allows)."""
    stack = [iter(page.children)]
    while stack:
        child = next(stack[-1], None)
        if child is None:
            stack.pop()
        elif child.tag == "page":
            stack.append(iter(child.children))
        else:
            yield child


def read_pnml(path: str | Path) -> PnmlNet:
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ProgramError([Problem(str(path), 0, "", f"cannot read PNML: {exc.strerror}")]
                           ) from None
    return parse_pnml(data, str(path))


def parse_pnml(data: bytes, file: str) -> PnmlNet:
    root = parse_xml(data, file)
    r = _Reader(file)
    net = root.child("net") if root.tag == "pnml" else None
    if net is None:
        raise ProgramError([Problem(file, root.line, root.tag,
                                    "expected <pnml> with a <net> element")])
    if net.attrs.get("type", "").rstrip("#/") not in (PTNET, PTNET.replace("2009", "2011")):
        r.problem(net, f"net type {net.attrs.get('type')!r}: only P/T nets ({PTNET}) are read")
    items: dict[str, _Item] = {}
    refs: dict[str, tuple[str, Node]] = {}
    places: list[_Item] = []
    transitions: list[_Item] = []
    arcs_raw: list[Node] = []
    initial: list[int] = []
    for el in (e for page in net.all("page") for e in _elements(page)):
        ident = el.attrs.get("id", "")
        if el.tag in ("place", "transition", "referencePlace", "referenceTransition"):
            if not ident:
                r.problem(el, f"<{el.tag}> without an id")
                continue
            if ident in items or ident in refs:
                r.problem(el, f"id {ident!r} is used twice")
                continue
        if el.tag in ("place", "transition"):
            item = _Item(ident, el.text_of("name", "text") or ident, el.line, el)
            items[ident] = item
            if el.tag == "place":
                places.append(item)
                initial.append(r.count(el, ("initialMarking", "text"), 0, "initial marking"))
            else:
                transitions.append(item)
        elif el.tag in ("referencePlace", "referenceTransition"):
            refs[ident] = (el.attrs.get("ref", ""), el)
        elif el.tag == "arc":
            arcs_raw.append(el)
    resolved = {i: _resolve(i, items, refs, r) for i in refs}
    pindex = {p.ident: k for k, p in enumerate(places)}
    tindex = {t.ident: k for k, t in enumerate(transitions)}
    arcs = []
    for el in arcs_raw:
        src = resolved.get(el.attrs.get("source", ""), el.attrs.get("source", ""))
        dst = resolved.get(el.attrs.get("target", ""), el.attrs.get("target", ""))
        weight = r.count(el, ("inscription", "text"), 1, "arc inscription")
        if weight == 0:
            r.problem(el, "arc inscription 0: expected a whole number > 0")
        if src in pindex and dst in tindex:
            arcs.append((pindex[src], tindex[dst], weight, False, el))
        elif src in tindex and dst in pindex:
            arcs.append((pindex[dst], tindex[src], weight, True, el))
        else:
            r.problem(el, f"arc {el.attrs.get('id', '?')}: source {src!r} and target {dst!r} "
                      "must be a place and a transition of this net")
    tool = r.tool_json(net, "program")
    if r.problems:
        raise ProgramError(r.problems)
    return PnmlNet(file, net.text_of("name", "text") or net.attrs.get("id", "net"), places,
                   initial, transitions, arcs, tool)


def _resolve(ident: str, items: dict[str, _Item], refs: dict[str, tuple[str, Node]],
             r: _Reader) -> str:
    seen = {ident}
    target, node = refs[ident]
    while target in refs:
        if target in seen:
            r.problem(node, f"reference {ident!r} is circular")
            return ""
        seen.add(target)
        target = refs[target][0]
    if target not in items:
        r.problem(node, f"reference {ident!r} names {target!r}, which is no place or transition")
    return target


def pt_analysis_net(net: PnmlNet) -> AnalysisNet:
    """The bare P/T skeleton (softplc data, if any, ignored)."""
    P, T = len(net.places), len(net.transitions)
    check_size(net.file, P, T)
    pre, post = np.zeros((T, P), np.int64), np.zeros((T, P), np.int64)
    for p, t, w, to_place, _ in net.arcs:
        (post if to_place else pre)[t, p] += w
    return from_pt(net.name, net.file, [(p.name, k, p.line) for p, k in
                                        zip(net.places, net.initial, strict=True)],
                   [(t.name, t.line) for t in net.transitions], pre, post)


def mapping_beside(path: Path) -> dict[str, Any] | None:
    """`NET.softplc.json` beside `NET.pnml`: {"io_image": ..., "places": {name: {...}},
    "transitions": {name: {...}}} with the keys of a program file, for running a net that
    another tool drew."""
    side = path.with_suffix(".softplc.json")
    if not side.exists():
        return None
    try:
        value = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ProgramError([Problem(str(side), getattr(exc, "lineno", 0), "",
                                    f"cannot read the mapping: {exc}")]) from None
    if not isinstance(value, dict):
        raise ProgramError([Problem(str(side), 1, "", "expected a JSON object")])
    return value


def compiled_net(net: PnmlNet, mapping: dict[str, Any] | None = None) -> CompiledNet:
    """The runnable program: the net's softplc data (toolspecific), overlaid by `mapping`."""
    r = _Reader(net.file)
    tool = dict(net.tool or {})
    mapping = mapping or {}
    io_ref = mapping.get("io_image", tool.get("io_image"))
    if not io_ref:
        raise ProgramError([Problem(net.file, 1, "net", "no io image: a softplc toolspecific "
                                    "<program> or a .softplc.json mapping must name one")])
    too_big = count_problem(net.file, 1, {"places": len(net.places),
                                          "transitions": len(net.transitions),
                                          "arcs": len(net.arcs)})
    if too_big is not None:  # before a program text of that size is written and parsed
        raise ProgramError([too_big])
    io = load_io_image(Path(net.file).parent / str(io_ref))
    places: dict[str, Any] = {}
    for item, tokens in zip(net.places, net.initial, strict=True):
        extra = r.tool_json(item.node, "place") or {}
        extra.update(mapping.get("places", {}).get(item.name, {}))
        spec: dict[str, Any] = {}
        if "records" in extra:
            spec["tokens"] = extra["records"]
            spec["coloured"] = True
        elif tokens:
            spec["tokens"] = tokens
        if "capacity" in extra:
            spec["capacity"] = extra["capacity"]
        if extra.get("outputs"):
            spec["outputs"] = {s: v for s, v in extra["outputs"]}
        places[item.name] = spec
    transitions: dict[str, Any] = {}
    arcs_of: list[list[tuple[int, int, int, bool, Node]]] = [[] for _ in net.transitions]
    for arc in net.arcs:
        arcs_of[arc[1]].append(arc)
    for t, item in enumerate(net.transitions):
        data = r.tool_json(item.node, "transition") or {}
        data.update(mapping.get("transitions", {}).get(item.name, {}))
        spec = {k: v for k, v in data.items() if k in ("priority", "when", "do", "delay",
                                                       "duration")}
        if data.get("outputs"):
            spec["outputs"] = {s: v for s, v in data["outputs"]}
        spec["from"] = [_arc_spec(net, r, p, w, a, "var") for p, _, w, to, a in arcs_of[t]
                        if not to]
        spec["to"] = [_arc_spec(net, r, p, w, a, "token") for p, _, w, to, a in arcs_of[t]
                      if to]
        for key in ("read", "inhibit"):
            if data.get(key):
                spec[key] = [{"place": p, "weight": w} for p, w in data[key]]
        transitions[item.name] = spec
    if r.problems:
        raise ProgramError(r.problems)
    program = {"program": net.name, "places": places, "transitions": transitions}
    if tool.get("events"):
        program["events"] = tool["events"]
    compiled = compile_text_with_io(json.dumps(program, indent=1), net.file, io)
    return dataclasses.replace(
        compiled, place_where=tuple((net.file, p.line) for p in net.places),
        transition_where=tuple((net.file, t.line) for t in net.transitions))


def _arc_spec(net: PnmlNet, r: _Reader, p: int, w: int, node: Node, key: str) -> Any:
    data = r.tool_json(node, "arc") or {}
    name = net.places[p].name
    if key in data:
        return {"place": name, key: data[key]}
    return name if w == 1 else {"place": name, "weight": w}


def load_for_analysis(path: str | Path) -> tuple[AnalysisNet, CompiledNet | None]:
    """A PNML file as an AnalysisNet: the program (scan semantics available) when softplc
    data is present or beside it, else the bare P/T net."""
    from softplc.analysis.model import from_compiled

    path = Path(path)
    net = read_pnml(path)
    mapping = mapping_beside(path)
    if net.tool is not None or mapping is not None:
        compiled = compiled_net(net, mapping)
        return from_compiled(compiled), compiled
    return pt_analysis_net(net), None


def structure(net: CompiledNet) -> tuple[Any, ...]:
    """Everything a CompiledNet runs by, in comparable form: export then import must give the
    same (the program hash differs: it is a digest of the source files' text)."""
    def trans(t: Any) -> tuple[Any, ...]:
        return (t.name, t.priority, tuple((a.place, a.weight, a.var) for a in t.pre),
                tuple((o.place, o.weight, o.var, None if o.fields is None else
                       tuple(sorted((k, c.text) for k, c in o.fields.items()))) for o in t.post),
                tuple(t.test), tuple(t.inhibit), None if t.guard is None else t.guard.text,
                tuple((a.kind, a.target, a.value.text if a.value else None) for a in t.actions),
                t.delay_ns, t.duration_ns, tuple(t.busy_outputs), t.coloured)
    return (net.name, net.place_names, tuple(int(x) for x in net.initial),
            tuple(int(x) for x in net.capacity), tuple(bool(x) for x in net.coloured),
            tuple(sorted((p, tuple(dict(r).items() for r in toks))
                         for p, toks in net.initial_tokens.items())),
            tuple(trans(t) for t in net.transitions), net.order,
            tuple(sorted(net.place_outputs.items())), tuple(sorted(net.emits)),
            tuple(sorted((s.name, str(s.address), s.type.value) for s in net.io.symbols.values())))
