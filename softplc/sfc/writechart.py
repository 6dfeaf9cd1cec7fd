"""A chart read from PLCopen XML -> PLCopen XML again (tc6_0201, the shape Beremiz writes).

Owns: writing a Chart back with the drawing of the file it was read from: the chart's steps
(initial), transitions with their ST conditions as written (inline; a named transition stays
named, with its ST body), action blocks with each action's qualifier and duration (a BOOL
variable by reference, an ST body inline or as the POU's action), the POU interface from the
chart's variables (located and unlocated, FB instances as declared, globals in a
configuration), and from the file: every object's localId, position and size, the
divergences, convergences and jumps, comments, each connection's routing points and each
pin's relPosition. Conditions that CODESYS wires from an inVariable are written inline (the
inVariable is left out); other FBD objects in an SFC body (the reader ignores them) too.
Does not know: the net, YAML; whether the chart is the one a net was compiled from
(export.py checks that before it calls write_chart).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Protocol, TypeVar
from xml.sax.saxutils import quoteattr

from softplc.core.errors import SoftplcError
from softplc.core.xmltree import Node, parse_xml
from softplc.sfc.graph import WIRING
from softplc.sfc.model import IEC_TYPES, Chart, Variable
from softplc.sfc.pous import choose_pou


class NotWritten(SoftplcError, ValueError):
    """The chart cannot be written back; `line` is where in its file."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(message)
        self.line, self.message = line, message


class _Lined(Protocol):
    @property
    def line(self) -> int: ...


T = TypeVar("T", bound=_Lined)
NS = "http://www.plcopen.org/xml/tc6_0201"
PINS = ("connectionPointIn", "connectionPointOut", "connectionPointOutAction")
_LOWER = {"STRING": "string", "WSTRING": "wstring"}  # the schema's two lower-case types
_ELEMENTARY = {"SINT", "USINT", "LINT", "ULINT", "BYTE", "LWORD", "DATE", "TOD", "DT",
               "TIME_OF_DAY", "DATE_AND_TIME", "LTIME"}


def cdata(text: str) -> str:
    return "<![CDATA[" + text.replace("]]>", "]]]]><![CDATA[>") + "]]>"


def _attrs(node: Node, *names: str) -> str:
    return "".join(f" {n}={quoteattr(node.attrs[n])}" for n in names if n in node.attrs)


def _xy(node: Node, tag: str) -> str:
    pos = node.child(tag)
    return "" if pos is None else f"<{tag}{_attrs(pos, 'x', 'y')}/>"


def pin(node: Node) -> str:
    """A connection point as drawn: its relPosition, each connection with its routing points."""
    conns = "".join(f"<connection{_attrs(c, 'refLocalId', 'formalParameter')}>"
                    + "".join(f"<position{_attrs(p, 'x', 'y')}/>" for p in c.all("position"))
                    + "</connection>" for c in node.all("connection"))
    return f"<{node.tag}{_attrs(node, 'formalParameter')}>{_xy(node, 'relPosition')}" \
        f"{conns}</{node.tag}>"


def _pins(node: Node, *tags: str) -> str:
    return "".join(pin(c) for tag in tags for c in node.all(tag))


def _st(text: str) -> str:
    return f"<ST><xhtml:p>{cdata(text)}</xhtml:p></ST>"


def write_chart(chart: Chart, data: bytes) -> str:
    """The chart as tc6_0201 XML; `data` is the file the chart was read from (its drawing)."""
    root = parse_xml(data, chart.file)
    return _Writer(chart, root, choose_pou(root, chart.file, chart.pou)).text()


class _Writer:
    def __init__(self, chart: Chart, root: Node, pou: Node) -> None:
        self.chart, self.root, self.pou = chart, root, pou
        self.sfc = pou.child("body").child("SFC")  # type: ignore[union-attr]  # a chart's POU
        # The reader's order: transitions, then the action blocks' actions, each object by
        # localId (the last of a repeated one); each pair checked by its XML line.
        objs = {n.attrs["localId"]: n for n in self.sfc.children  # type: ignore[union-attr]
                if "localId" in n.attrs}
        for n in objs.values():
            if n.tag == "macroStep":
                raise NotWritten(n.line, f"macro step {n.attrs.get('name', '')!r}: a chart "
                                 "with macro steps is not written back (softplc inlines their "
                                 "bodies; the flattened names are no IEC identifiers)")
        graphic = [a.line for a in chart.actions if not a.step] + [  # reader.py, sfc/fbd.py
            t.line for g in pou.all("transitions") for t in g.all("transition")
            if (b := t.child("body")) is not None and b.child("ST") is None]
        if graphic:
            raise NotWritten(graphic[0], "function blocks wired into conditions and FBD/LD "
                             "named transitions are not written back (softplc reads them as ST "
                             "and the blocks' calls; the network's drawing is not kept)")
        self.trans = _paired([n for n in objs.values() if n.tag == "transition"],
                             chart.transitions)
        self.acts = _paired([a for b in objs.values() if b.tag == "actionBlock"
                             for a in b.all("action")], chart.actions)
        self.steps = {s.name: s for s in chart.steps}

    def text(self) -> str:
        body = "\n".join(filter(None, (self.obj(n) for n in self.sfc.children)))  # type: ignore[union-attr]
        name = self.pou.attrs.get("name", self.chart.pou)
        return f"""<?xml version='1.0' encoding='utf-8'?>
<!-- Written by softplc from {_comment_safe(self.chart.file)} (docs/sfc.md, export). -->
<project xmlns={quoteattr(NS)} xmlns:xhtml="http://www.w3.org/1999/xhtml" \
xmlns:xsd="http://www.w3.org/2001/XMLSchema">
<fileHeader companyName="softplc" productName="softplc" productVersion="1" \
creationDateTime="1970-01-01T00:00:00"/>
<contentHeader name={quoteattr(self.header_name())}><coordinateInfo>{self.scaling()}\
</coordinateInfo></contentHeader>
<types><dataTypes/><pous><pou name={quoteattr(name)} pouType=\
{quoteattr(self.pou.attrs.get("pouType", "program"))}>
<interface>{self.interface()}</interface>
{self.bodies("actions", "action")}{self.bodies("transitions", "transition")}<body><SFC>
{body}
</SFC></body></pou></pous></types>
<instances><configurations>{self.configuration(name)}</configurations></instances>
</project>
"""

    def header_name(self) -> str:
        head = self.root.child("contentHeader")
        return head.attrs.get("name", self.chart.pou) if head is not None else self.chart.pou

    def scaling(self) -> str:
        info = (self.root.child("contentHeader") or Node("", {}, 0)).child("coordinateInfo")
        out = []
        for lang in ("fbd", "ld", "sfc"):
            given = info.child(lang) if info is not None else None
            scale = given.child("scaling") if given is not None else None
            xy = _attrs(scale, "x", "y") if scale is not None else ' x="0" y="0"'
            out.append(f"<{lang}><scaling{xy}/></{lang}>")
        return "".join(out)

    # The POU: interface, actions, transitions.
    def interface(self) -> str:
        docs = {v.attrs.get("name", "").upper(): d.all_text().strip() for v in self.pou.walk()
                if v.tag == "variable" and (d := v.child("documentation")) is not None}
        groups: list[tuple[str, list[str]]] = []
        for v in sorted(self.chart.variables.values(), key=lambda v: v.line):
            if v.section == "globalVars":
                continue
            if not groups or groups[-1][0] != v.section:
                groups.append((v.section, []))
            groups[-1][1].append(variable(v, docs.get(v.name.upper())))
        return "".join(f"<{k}>{''.join(vs)}</{k}>" for k, vs in groups)

    def bodies(self, tag: str, item: str) -> str:
        out = [f"<{item} name={quoteattr(n.attrs.get('name', ''))}><body>"
               f"{_st(st.all_text().strip())}</body></{item}>"
               for group in self.pou.all(tag) for n in group.all(item)
               if (b := n.child("body")) is not None and (st := b.child("ST")) is not None]
        return f"<{tag}>{''.join(out)}</{tag}>\n" if out else ""

    def configuration(self, pou: str) -> str:
        task = next((t for t in self.root.walk() if t.tag == "task" and any(
            i.attrs.get("typeName", "").upper() == pou.upper() for i in t.all("pouInstance"))),
            None)
        attrs = _attrs(task, "name", "priority", "interval") if task is not None else \
            ' name="task0" priority="0" interval="T#10ms"'
        inst = next((i for i in task.all("pouInstance")), None) if task is not None else None
        iname = inst.attrs.get("name", "instance0") if inst is not None else "instance0"
        globs = "".join(variable(v, None) for v in sorted(
            self.chart.variables.values(), key=lambda v: v.line) if v.section == "globalVars")
        return f'<configuration name="config"><resource name="resource1"><task{attrs}>' \
            f'<pouInstance name={quoteattr(iname)} typeName={quoteattr(pou)}/></task>' \
            f'</resource>{f"<globalVars>{globs}</globalVars>" if globs else ""}' \
            '</configuration>'

    # The SFC body, object by object in the file's order.
    def obj(self, n: Node) -> str:
        head = f"{_attrs(n, 'localId', 'height', 'width')}>{_xy(n, 'position')}"
        if n.tag == "step":
            step = self.steps[n.attrs.get("name", "")]
            return f'<step{_attrs(n, "localId")} name={quoteattr(step.name)} initialStep=' \
                f'"{"true" if step.initial else "false"}"{_attrs(n, "height", "width")}>' \
                f'{_xy(n, "position")}{_pins(n, *PINS)}</step>'
        if n.tag == "transition":
            return f"<transition{_attrs(n, 'localId', 'height', 'width', 'priority')}>" \
                f"{_xy(n, 'position')}{_pins(n, *PINS[:2])}{self.condition(n)}</transition>"
        if n.tag in WIRING:
            return f"<{n.tag}{head}{_pins(n, *PINS[:2])}</{n.tag}>"
        if n.tag == "jumpStep":
            return f"<jumpStep{_attrs(n, 'localId', 'targetName', 'height', 'width')}>" \
                f"{_xy(n, 'position')}{_pins(n, PINS[0])}</jumpStep>"
        if n.tag == "actionBlock":
            return f"<actionBlock{head}{_pins(n, PINS[0])}" \
                f"{''.join(self.action(a) for a in n.all('action'))}</actionBlock>"
        if n.tag == "comment":
            text = (n.child("content") or n).all_text().strip()
            return f"<comment{head}<content><xhtml:p>{cdata(text)}</xhtml:p></content></comment>"
        return ""  # an inVariable wired into a condition (written inline), or FBD the reader skips

    def condition(self, n: Node) -> str:
        cond = n.child("condition")
        ref = cond.child("reference") if cond is not None else None
        if cond is not None and ref is not None:
            return f"<condition{_attrs(cond, 'negated')}><reference" \
                f"{_attrs(ref, 'name')}/></condition>"
        text = self.trans[id(n)].condition.strip()
        return f'<condition><inline name="">{_st(text)}</inline></condition>'

    def action(self, a: Node) -> str:
        act = self.acts[id(a)]
        duration = f" duration={quoteattr(act.duration)}" if act.duration else ""
        ref, inline = a.child("reference"), a.child("inline")
        if ref is not None:
            what = f"<reference{_attrs(ref, 'name')}/>"
        else:
            st = inline.child("ST") if inline is not None else None
            what = f"<inline>{_st(st.all_text().strip() if st is not None else '')}</inline>"
        return f"<action{_attrs(a, 'localId')} qualifier={quoteattr(act.qualifier)}{duration}>" \
            f"{_xy(a, 'relPosition')}{what}{_pins(a, PINS[1])}</action>"


def _paired(nodes: list[Node], items: Sequence[T]) -> dict[int, T]:
    """Each XML object -> the chart's item read from it (the same order, the same line)."""
    if len(nodes) != len(items) or any(n.line != i.line for n, i in zip(nodes, items, strict=True)):
        raise NotWritten(nodes[0].line if nodes else 1, "the chart's transitions and actions "
                         "do not pair with the file's objects")
    return {id(n): i for n, i in zip(nodes, items, strict=True)}


def variable(v: Variable, doc: str | None) -> str:
    iec = v.iec.upper()
    typ = f"<{_LOWER.get(iec, iec)}/>" if iec in IEC_TYPES or iec in _LOWER or iec in \
        _ELEMENTARY else f"<derived name={quoteattr(v.iec)}/>"
    init = f"<initialValue><simpleValue value={quoteattr(v.init)}/></initialValue>" \
        if v.init is not None else ""
    docs = f"<documentation><xhtml:p>{cdata(doc)}</xhtml:p></documentation>" if doc else ""
    address = f" address={quoteattr(v.address)}" if v.address else ""
    return f"<variable name={quoteattr(v.name)}{address}><type>{typ}</type>{init}{docs}" \
        "</variable>"


def _comment_safe(text: str) -> str:
    """A file name inside an XML comment, which may not hold `--`."""
    return re.sub("-(?=-)", "- ", text)
