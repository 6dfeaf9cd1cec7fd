"""Writes PLCopen TC6 XML charts for tests, wired as the editors wire them.

A chart is steps, transitions (sources, targets, ST condition) and actions; the writer uses
the constructs the editors use: a selectionDivergence where a step has several single-step
exits, a selectionConvergence where several transitions enter one step, a
simultaneousConvergence for several preceding steps, a simultaneousDivergence with jumpSteps
for several following steps, jumpSteps back to steps already entered.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from xml.sax.saxutils import quoteattr

NS = {"tc6_0201": "http://www.plcopen.org/xml/tc6_0201",
      "tc6_0200": "http://www.plcopen.org/xml/tc6_0200",
      "tc6": "http://www.plcopen.org/xml/tc6.xsd"}


@dataclass
class ChartSpec:
    steps: list[str]
    initial: list[str]
    transitions: list[tuple[list[str], list[str], str]]  # sources, targets, ST condition
    actions: list[tuple[str, str, str]] = field(default_factory=list)  # step, qualifier, name
    # name -> (IEC type, address or "")
    variables: dict[str, tuple[str, str]] = field(default_factory=dict)
    bodies: dict[str, str] = field(default_factory=dict)  # POU action name -> ST body
    pou: str = "Chart"


def _cond(text: str) -> str:
    return ('<condition><inline name=""><ST><xhtml:p><![CDATA[' + text +
            ']]></xhtml:p></ST></inline></condition>')


def chart_xml(spec: ChartSpec, ns: str = "tc6_0201") -> str:
    ids = iter(range(1, 100_000))
    step_id = {s: next(ids) for s in spec.steps}
    t_id = [next(ids) for _ in spec.transitions]
    out: list[str] = []
    exits: dict[str, list[int]] = {}
    for i, (src, _tgt, _c) in enumerate(spec.transitions):
        if len(src) == 1:
            exits.setdefault(src[0], []).append(i)
    entries: dict[str, list[int]] = {}
    for i, (_src, tgt, _c) in enumerate(spec.transitions):
        if len(tgt) == 1:
            entries.setdefault(tgt[0], []).append(i)
    div = {s: next(ids) for s, ts in exits.items() if len(ts) > 1}
    for s, d in div.items():
        out.append(f'<selectionDivergence localId="{d}"><connectionPointIn><connection '
                   f'refLocalId="{step_id[s]}"/></connectionPointIn></selectionDivergence>')
    for s in spec.steps:
        inputs = entries.get(s, [])
        ref = ""
        if len(inputs) == 1:
            ref = f'<connection refLocalId="{t_id[inputs[0]]}"/>'
        elif inputs:
            c = next(ids)
            pins = "".join(f'<connectionPointIn><connection refLocalId="{t_id[i]}"/>'
                           '</connectionPointIn>' for i in inputs)
            out.append(f'<selectionConvergence localId="{c}">{pins}</selectionConvergence>')
            ref = f'<connection refLocalId="{c}"/>'
        init = "true" if s in spec.initial else "false"
        out.append(f'<step localId="{step_id[s]}" name="{s}" initialStep="{init}">'
                   f'<connectionPointIn>{ref}</connectionPointIn><connectionPointOut/>'
                   '<connectionPointOutAction/></step>')
    for i, (src, tgt, cond) in enumerate(spec.transitions):
        if len(src) == 1:
            pred = div.get(src[0], step_id[src[0]])
        else:
            pred = next(ids)
            pins = "".join(f'<connectionPointIn><connection refLocalId="{step_id[s]}"/>'
                           '</connectionPointIn>' for s in src)
            out.append(f'<simultaneousConvergence localId="{pred}">{pins}'
                       '</simultaneousConvergence>')
        out.append(f'<transition localId="{t_id[i]}"><position x="{10 * i}" y="0"/>'
                   f'<connectionPointIn><connection refLocalId="{pred}"/></connectionPointIn>'
                   f'<connectionPointOut/>{_cond(cond)}</transition>')
        if len(tgt) > 1:
            d = next(ids)
            out.append(f'<simultaneousDivergence localId="{d}"><connectionPointIn><connection '
                       f'refLocalId="{t_id[i]}"/></connectionPointIn></simultaneousDivergence>')
            for s in tgt:
                out.append(f'<jumpStep localId="{next(ids)}" targetName="{s}"><connectionPointIn>'
                           f'<connection refLocalId="{d}"/></connectionPointIn></jumpStep>')
    for step, qual, name in spec.actions:
        qual, _, duration = qual.partition("@")  # "L@T#30ms": qualifier L, duration T#30ms
        q = (f' qualifier="{qual}"' if qual != "N" else "") + \
            (f' duration="{duration}"' if duration else "")
        out.append(f'<actionBlock localId="{next(ids)}"><connectionPointIn><connection '
                   f'refLocalId="{step_id[step]}"/></connectionPointIn><action localId="0"{q}>'
                   f'<reference name="{name}"/></action></actionBlock>')
    return _project(spec, ns, "\n".join(out))


def _project(spec: ChartSpec, ns: str, body: str) -> str:
    def var(name: str, typ: str, addr: str) -> str:
        a = f" address={quoteattr(addr)}" if addr else ""
        return f'<variable name="{name}"{a}><type><{typ}/></type></variable>'
    local = "".join(var(n, t, a) for n, (t, a) in spec.variables.items())
    actions = "".join(f'<action name="{n}"><body><ST><xhtml:p><![CDATA[{b}]]></xhtml:p></ST>'
                      '</body></action>' for n, b in spec.bodies.items())
    return f"""<?xml version="1.0" encoding="utf-8"?>
<project xmlns="{NS[ns]}" xmlns:xhtml="http://www.w3.org/1999/xhtml">
<fileHeader companyName="softplc tests" productName="chartxml" productVersion="1"
 creationDateTime="2026-01-01T00:00:00"/>
<types><dataTypes/><pous>
<pou name="{spec.pou}" pouType="program">
<interface><localVars>{local}</localVars></interface>
<actions>{actions}</actions>
<body><SFC>
{body}
</SFC></body></pou></pous></types></project>
"""
