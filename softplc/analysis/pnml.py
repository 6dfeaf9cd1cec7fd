"""PNML (ISO/IEC 15909-2) import; export lives in pnml_export.py, whose functions callers
also import from here; other tools' net types and label styles in pnml_dialects.py.

Owns: reading PNML (places and transitions under <net> or in pages, nested pages, reference
places and transitions) into a bare P/T AnalysisNet (same-named nodes told apart by id),
or, with softplc's data (in toolspecific, or a `NET.softplc.json` mapping beside the file),
into a CompiledNet through the program compiler (io image beside it, or embedded).
Every problem is located (file:line).
Does not know: how PNML is written, exploration, the CLI.
"""

from __future__ import annotations

import dataclasses
import json
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from softplc.analysis.model import AnalysisNet, check_size, from_pt
from softplc.analysis.pnml_dialects import (
    PT_TYPES,
    arc_kind,
    elements,
    label,
    normal_type,
    pipe_count,
    type_problem,
)
from softplc.analysis.pnml_encode import decoded
from softplc.analysis.pnml_export import TOOL
from softplc.analysis.pnml_export import export_compiled as export_compiled
from softplc.analysis.pnml_export import export_pt as export_pt
from softplc.analysis.pnml_export import structure as structure
from softplc.core.net import CompiledNet
from softplc.core.problems import Problem, ProgramError
from softplc.core.symbols import IoImage
from softplc.core.xmltree import Node, parse_xml
from softplc.program.compiler import compile_text_with_io
from softplc.program.io_image import load_io_image, parse_io_image
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
    inhibit: list[tuple[int, int, int]] = dataclasses.field(default_factory=list)  # p, t, w
    capacity: list[int] = dataclasses.field(default_factory=list)  # per place, -1: none
    notes: list[str] = dataclasses.field(default_factory=list)
    line: int = 1  # the <net> element's: findings about the whole net point there


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

    def count(self, node: Node, tag: str, default: int, what: str) -> int:
        text = label(node, tag)
        if text is None or text == "":
            return default
        text, why = pipe_count(text)
        if why is not None:
            self.problem(node.child(tag) or node, f"{what} {why}")
            return default
        if not text.isdigit():
            self.problem(node.child(tag) or node, f"{what} {text!r}: expected a whole "
                         "number >= 0" + ("" if what == "initial marking" else " (> 0)"))
            return default
        return int(text)


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
    why = type_problem(net.attrs.get("type"))
    if why is not None:
        raise ProgramError([Problem(file, net.line, "net", why)])
    items: dict[str, _Item] = {}
    refs: dict[str, tuple[str, Node]] = {}
    places: list[_Item] = []
    transitions: list[_Item] = []
    arcs_raw: list[Node] = []
    initial: list[int] = []
    capacity: list[int] = []
    notes: list[str] = []
    for el in elements(net):
        ident = el.attrs.get("id", "")
        if el.tag in ("place", "transition", "referencePlace", "referenceTransition"):
            if not ident:
                r.problem(el, f"<{el.tag}> without an id")
                continue
            if ident in items or ident in refs:
                r.problem(el, f"id {ident!r} is used twice")
                continue
        if el.tag in ("place", "transition"):
            item = _Item(ident, label(el, "name") or ident, el.line, el)
            items[ident] = item
            if el.tag == "place":
                places.append(item)
                initial.append(r.count(el, "initialMarking", 0, "initial marking"))
                capacity.append(r.count(el, "capacity", 0, "capacity") or -1)  # PIPE: 0 = none
                if 0 <= capacity[-1] < initial[-1]:
                    r.problem(el, f"initial marking {initial[-1]} exceeds the capacity "
                              f"{capacity[-1]}")
            else:
                transitions.append(item)
        elif el.tag in ("referencePlace", "referenceTransition"):
            refs[ident] = (el.attrs.get("ref", ""), el)
        elif el.tag == "arc":
            arcs_raw.append(el)
        elif el.tag == "net":  # a WoPeD subprocess: <page id=TRANSITION><net>...
            notes.append(f"{file}:{el.line}: a net inside a page (a WoPeD subprocess) is not "
                         "read: its transition stands for it")
    if not places and not transitions and not r.problems:
        r.problem(net, "no place and no transition (looked under <net> and in its <page>s): "
                  "an empty net is not analysed")
    resolved = {i: _resolve(i, items, refs, r) for i in refs}
    pindex = {p.ident: k for k, p in enumerate(places)}
    tindex = {t.ident: k for k, t in enumerate(transitions)}
    arcs = []
    inhibit = []
    for el in arcs_raw:
        src = resolved.get(el.attrs.get("source", ""), el.attrs.get("source", ""))
        dst = resolved.get(el.attrs.get("target", ""), el.attrs.get("target", ""))
        weight = r.count(el, "inscription", 1, "arc inscription")
        kind = arc_kind(el)
        if weight == 0:
            r.problem(el, "arc inscription 0: expected a whole number > 0")
        if kind not in ("normal", "inhibitor"):
            r.problem(el, f"arc {el.attrs.get('id', '?')}: {kind} arcs are not read (only "
                      "normal and inhibitor arcs)")
        elif src in pindex and dst in tindex:
            if kind == "inhibitor":
                inhibit.append((pindex[src], tindex[dst], weight))
            else:
                arcs.append((pindex[src], tindex[dst], weight, False, el))
        elif src in tindex and dst in pindex and kind == "normal":
            arcs.append((pindex[dst], tindex[src], weight, True, el))
        else:
            r.problem(el, f"arc {el.attrs.get('id', '?')}: source {src!r} and target {dst!r} "
                      "must be a place and a transition of this net" +
                      (" (an inhibitor arc: place to transition)" if kind != "normal" else ""))
    tool = r.tool_json(net, "program")
    if r.problems:
        raise ProgramError(r.problems)
    dialect = PT_TYPES[normal_type(net.attrs.get("type", ""))]
    if dialect == "pnmlcoremodel":
        notes.append("pnmlcoremodel net: initial markings and inscriptions read as P/T "
                     "(as ProM and pm4py write them)")
    if dialect == "PIPE":
        notes.append("PIPE net: rates, timing and priorities not read; analysed as a P/T net")
    return PnmlNet(file, label(net, "name") or net.attrs.get("id", "net"), places,
                   initial, transitions, arcs, tool, inhibit, capacity, notes, net.line or 1)


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


def shown_names(items: list[_Item]) -> list[str]:
    """Names to report nodes by: the name, or "name [id]" where names repeat (WoPeD's
    operators, hand-drawn nets), so that no two places share a bound or a marking entry."""
    counts = Counter(i.name for i in items)
    shown = [i.name if counts[i.name] == 1 else f"{i.name} [{i.ident}]" for i in items]
    if len(set(shown)) < len(shown):  # a name that looks like another's "name [id]"
        shown = [f"{i.name} [{i.ident}]" for i in items]
    return shown


def pt_analysis_net(net: PnmlNet, *notes: str) -> AnalysisNet:
    """The bare P/T skeleton (softplc data, if any, ignored)."""
    P, T = len(net.places), len(net.transitions)
    check_size(net.file, P, T)
    pre, post = np.zeros((T, P), np.int64), np.zeros((T, P), np.int64)
    inhibit = np.zeros((T, P), np.int64)
    for p, t, w, to_place, _ in net.arcs:
        (post if to_place else pre)[t, p] += w
    for p, t, w in net.inhibit:
        inhibit[t, p] = w if inhibit[t, p] == 0 else min(int(inhibit[t, p]), w)
    bare = from_pt(net.name, net.file,
                   [(n, k, p.line) for n, p, k in
                    zip(shown_names(net.places), net.places, net.initial, strict=True)],
                   [(n, t.line) for n, t in zip(shown_names(net.transitions), net.transitions,
                                                strict=True)], pre, post, inhibit)
    capacity = np.array(net.capacity or [-1] * P, np.int64)
    return dataclasses.replace(bare, capacity=capacity, line=net.line,
                               notes=(*bare.notes, *net.notes, *notes))


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
    net = decoded(net, r.tool_json)  # without the export's P/T encodings (pnml_encode.py)
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
    for kind, items in (("place", net.places), ("transition", net.transitions)):
        first: dict[str, str] = {}
        for item in items:
            if first.setdefault(item.name, item.ident) != item.ident:
                r.problem(item.node, f"{kind} name {item.name!r} is also {kind} "
                          f"{first[item.name]!r}'s: a program's {kind}s need distinct names")
    if r.problems:
        raise ProgramError(r.problems)
    io = _io_image(net, str(io_ref), tool)
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
        elif net.capacity and net.capacity[len(places)] >= 0:
            spec["capacity"] = net.capacity[len(places)]
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
        drawn = [{"place": net.places[p].name, "weight": w} for p, u, w in net.inhibit if u == t]
        if drawn:
            spec["inhibit"] = [*spec.get("inhibit", []), *drawn]
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


def _io_image(net: PnmlNet, io_ref: str, tool: dict[str, Any]) -> IoImage:
    """The symbols file named (relative to the PNML file) or, where it is missing, the copy
    `softplc export` embeds (toolspecific `io_image_text`)."""
    path = Path(net.file).parent / io_ref
    embedded = tool.get("io_image_text")
    if path.exists() or not isinstance(embedded, str):
        return load_io_image(path)
    return parse_io_image(embedded, f"{net.file}#{io_ref}")


def _io_missing(path: Path, net: PnmlNet, mapping: dict[str, Any] | None) -> str | None:
    """The io image a net's softplc data names when it is neither beside it nor embedded."""
    tool = net.tool or {}
    io_ref = (mapping or {}).get("io_image", tool.get("io_image"))
    if not io_ref or (path.parent / str(io_ref)).exists() or "io_image_text" in tool:
        return None
    return str(io_ref)


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
    missing = _io_missing(path, net, mapping) if net.tool or mapping else None
    if missing is not None:
        return pt_analysis_net(net, f"io image {missing} not found beside {path.name} and not "
                               "embedded: its P/T skeleton analysed (softplc's guards, "
                               "actions, timing and priorities ignored; capacities, read and "
                               "inhibitor arcs as the export encodes them)"), None
    if net.tool is not None or mapping is not None:
        compiled = compiled_net(net, mapping)
        return from_compiled(compiled), compiled
    return pt_analysis_net(net), None
