"""PNML (ISO/IEC 15909-2, `ptnet` type) export.

Owns: writing a CompiledNet (or a bare PtNet) as PNML: the P/T skeleton any tool opens
(places, transitions, weighted arcs, initial markings, names; capacities, read arcs and the
inhibitor arcs it can say encoded as pnml_encode.py decides) plus softplc's own data in
`toolspecific tool="softplc"` elements (guards, actions, timing, priorities, outputs,
capacities, coloured tokens, test and inhibitor arcs, the io image); the namespaces and the
tool name that pnml.py reads back; `structure`, what a round trip must keep.
Does not know: reading PNML, exploration, the CLI.
"""

from __future__ import annotations

import json
from typing import Any
from xml.sax.saxutils import escape, quoteattr

from softplc.analysis.models import PtNet
from softplc.analysis.pnml_encode import encoding
from softplc.core.net import ActionKind, CompiledNet

PNML_NS = "http://www.pnml.org/version-2009/grammar/pnml"
PTNET = "http://www.pnml.org/version-2009/grammar/ptnet"
TOOL = "softplc"


def _tool(body: str, indent: str) -> str:
    return f'{indent}<toolspecific tool="{TOOL}" version="1">{body}</toolspecific>\n'


def _named(kind: str, ident: str, name: str, inner: str, indent: str) -> str:
    return (f'{indent}<{kind} id="{ident}"><name><text>{escape(name)}</text></name>\n'
            f"{inner}{indent}</{kind}>\n")


def _json_tag(tag: str, value: Any) -> str:
    return f"<{tag}>{escape(json.dumps(value, sort_keys=True))}</{tag}>"


def _action_text(kind: ActionKind, target: str, value_text: str | None) -> str:
    if kind is ActionKind.WRITE:
        return f"{target} = {value_text}"
    return f"{kind.value} {target}"


def export_compiled(net: CompiledNet, io_image: str | None = None,
                    io_text: str | None = None) -> str:
    """PNML text of `net`. `io_image`: the symbols file as the importer should find it
    (relative to the PNML file); default: the path the program gave, made relative.
    `io_text`: that file's text, embedded so that the net still compiles where the file is
    not beside it (a net copied elsewhere)."""
    enc = encoding(net)
    io_ref = io_image if io_image is not None else net.io.path
    program: dict[str, Any] = {"name": net.name, "io_image": io_ref, "events": sorted(net.emits)}
    if io_text is not None:
        program["io_image_text"] = io_text
    head = _json_tag("program", program)
    out = [f'<?xml version="1.0" encoding="UTF-8"?>\n<pnml xmlns="{PNML_NS}">\n',
           f'  <net id="{_id(net.name)}" type="{PTNET}">\n',
           f"    <name><text>{escape(net.name)}</text></name>\n", _tool(head, "    "),
           '    <page id="page0">\n']
    ind = "      "
    for p, name in enumerate(net.place_names):
        extra: dict[str, Any] = {}
        if net.capacity[p] >= 0:
            extra["capacity"] = int(net.capacity[p])
        if net.place_outputs.get(p):
            extra["outputs"] = [[s, v] for s, v in net.place_outputs[p]]
        if net.coloured[p]:
            extra["records"] = [dict(r) for r in net.initial_tokens.get(p, ())]
        inner = f"{ind}  <initialMarking><text>{int(net.initial[p])}</text></initialMarking>\n"
        if extra:
            inner += _tool(_json_tag("place", extra), ind + "  ")
        out.append(_named("place", f"p{p}", name, inner, ind))
    for t in net.transitions:
        data: dict[str, Any] = {"priority": t.priority}
        if t.guard is not None:
            data["when"] = t.guard.text
        if t.actions:
            data["do"] = [_action_text(a.kind, a.target, a.value.text if a.value else None)
                          for a in t.actions]
        for key, ns in (("delay", t.delay_ns), ("duration", t.duration_ns)):
            if ns:
                data[key] = f"{ns}ns"
        if t.busy_outputs:
            data["outputs"] = [[s, v] for s, v in t.busy_outputs]
        if t.test:
            data["read"] = [[net.place_names[p], w] for p, w in t.test]
        if t.inhibit:
            data["inhibit"] = [[net.place_names[p], w] for p, w in t.inhibit]
        out.append(_named("transition", f"t{t.index}", t.name,
                          _tool(_json_tag("transition", data), ind + "  "), ind))
    for c, (p, free) in enumerate(enc.complements):
        inner = (f"{ind}  <initialMarking><text>{free}</text></initialMarking>\n"
                 + _tool(_json_tag("place", {"complement_of": net.place_names[p]}), ind + "  "))
        out.append(_named("place", f"c{c}", f"{net.place_names[p]} (free)", inner, ind))
    arcs: list[tuple[str, str, int, dict[str, Any]]] = []
    for t in net.transitions:
        pending = {(p, to): e for (u, p, to), e in enc.extra.items() if u == t.index}
        for a in t.pre:
            spec: dict[str, Any] = {"var": a.var} if a.var else {}
            _encodes(spec, pending.pop((a.place, False), 0))
            arcs.append((f"p{a.place}", f"t{t.index}", a.weight + spec.get("encodes", 0), spec))
        for o in t.post:
            spec = {}
            if o.var is not None:
                spec["token"] = o.var
            elif o.fields is not None:
                spec["token"] = {k: c.text for k, c in o.fields.items()}
            _encodes(spec, pending.pop((o.place, True), 0))
            arcs.append((f"t{t.index}", f"p{o.place}", o.weight + spec.get("encodes", 0), spec))
        for (p, to_place), e in sorted(pending.items()):  # a read arc's pair, on its own
            ends = (f"t{t.index}", f"p{p}") if to_place else (f"p{p}", f"t{t.index}")
            arcs.append((*ends, e, {"encodes": e}))
        for u, c, to_place, w in enc.arcs:
            if u == t.index:
                ends = (f"t{t.index}", f"c{c}") if to_place else (f"c{c}", f"t{t.index}")
                arcs.append((*ends, w, {}))
    for n, (src, dst, weight, spec) in enumerate(arcs):
        tool = _tool(_json_tag("arc", spec), ind + "  ") if spec else ""
        out.append(_arc(f"a{n}", src, dst, weight, tool, ind))
    out.append("    </page>\n  </net>\n</pnml>\n")
    return "".join(out)


def _encodes(spec: dict[str, Any], extra: int) -> None:
    if extra:
        spec["encodes"] = extra


def export_pt(net: PtNet) -> str:
    """PNML text of a bare P/T net (the benchmark models)."""
    ids = {p: f"p{i}" for i, (p, _) in enumerate(net.places)}
    out = [f'<?xml version="1.0" encoding="UTF-8"?>\n<pnml xmlns="{PNML_NS}">\n',
           f'  <net id="{_id(net.name)}" type="{PTNET}">\n',
           f"    <name><text>{escape(net.name)}</text></name>\n", '    <page id="page0">\n']
    ind = "      "
    for p, k in net.places:
        out.append(_named("place", ids[p], p, f"{ind}  <initialMarking><text>{k}</text>"
                          "</initialMarking>\n", ind))
    n = 0
    for i, (t, pre, post) in enumerate(net.transitions):
        out.append(_named("transition", f"t{i}", t, "", ind))
        for p, w in pre.items():
            out.append(_arc(f"a{n}", ids[p], f"t{i}", w, "", ind))
            n += 1
        for p, w in post.items():
            out.append(_arc(f"a{n}", f"t{i}", ids[p], w, "", ind))
            n += 1
    out.append("    </page>\n  </net>\n</pnml>\n")
    return "".join(out)


def _arc(ident: str, source: str, target: str, weight: int, tool: str, ind: str) -> str:
    inscription = (f"{ind}  <inscription><text>{weight}</text></inscription>\n"
                   if weight != 1 else "")
    return (f"{ind}<arc id={quoteattr(ident)} source={quoteattr(source)} "
            f"target={quoteattr(target)}>\n{inscription}{tool}{ind}</arc>\n")


def _id(name: str) -> str:
    clean = "".join(c if c.isalnum() or c in "_-." else "_" for c in name)
    return clean if clean[:1].isalpha() else "n" + clean


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
