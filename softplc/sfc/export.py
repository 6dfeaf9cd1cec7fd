"""A compiled net -> PLCopen TC6 XML (tc6_0201, the shape Beremiz writes), when it is an SFC.

A net compiled from a PLCopen chart that still compiles to this very net (same program hash)
is written back from the chart (writechart.py: actions of every qualifier, ST bodies, the
drawing); every other net goes through the inference below.
Owns: deciding whether a net is a chart (one-token places, weight-1 arcs, no data, no
durations, actions only as Moore BOOL outputs, guards in the ST subset, a delay only as a
step timer) with a located reason for each place or transition that is not, and writing the
chart: steps, transitions with inline ST, divergences and convergences, jumps, N actions,
located variables. The inverse of the mapping in docs/sfc.md, for the part that has one.
The drawing: a net compiled from a PLCopen chart keeps each step's and transition's
`<position>` (read again from the chart, by name); the wiring objects the writer adds are
placed beside them; a net written in YAML is laid out in one column.
Does not know: how the net was written, beyond its source being a PLCopen file.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path
from xml.sax.saxutils import quoteattr

from softplc.core.errors import SoftplcError
from softplc.core.net import CompiledNet, InputArc, OutputArc, Transition
from softplc.core.problems import Problem, ProgramError
from softplc.sfc.load import is_plcopen
from softplc.sfc.reader import read_chart
from softplc.sfc.writechart import NotWritten, write_chart

_IEC = {"bool": "BOOL", "int": "INT", "word": "UINT", "dint": "DINT", "udint": "UDINT",
        "real": "REAL", "lreal": "LREAL"}
_CMP = {ast.Eq: "=", ast.NotEq: "<>", ast.Lt: "<", ast.Gt: ">", ast.LtE: "<=", ast.GtE: ">="}
_ARITH = {ast.Add: "+", ast.Sub: "-", ast.Mult: "*"}


class _NotSt(SoftplcError, ValueError):
    """A guard construct with no ST form (its text is the message)."""


def st_of(text: str) -> str:
    """A softplc guard in ST (the subset docs/sfc.md lists); _NotSt for anything else."""
    return _st(ast.parse(text, mode="eval").body)


def _st(node: ast.expr) -> str:
    if isinstance(node, ast.BoolOp):
        word = " AND " if isinstance(node.op, ast.And) else " OR "
        return "(" + word.join(_st(v) for v in node.values) + ")"
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.Not | ast.USub):
        return ("NOT " if isinstance(node.op, ast.Not) else "-") + f"({_st(node.operand)})"
    if isinstance(node, ast.Compare) and len(node.ops) == 1 and type(node.ops[0]) in _CMP:
        return f"({_st(node.left)} {_CMP[type(node.ops[0])]} {_st(node.comparators[0])})"
    if isinstance(node, ast.BinOp) and type(node.op) in _ARITH:
        return f"({_st(node.left)} {_ARITH[type(node.op)]} {_st(node.right)})"
    if isinstance(node, ast.Name):
        return {"true": "TRUE", "false": "FALSE"}.get(node.id, node.id)
    if isinstance(node, ast.Constant) and isinstance(node.value, bool | int | float):
        return str(node.value).upper() if isinstance(node.value, bool) else repr(node.value)
    raise _NotSt(ast.unparse(node))


def export_plcopen(net: CompiledNet,
                   compile_file: Callable[[str], CompiledNet] | None = None) -> str:
    """The chart's XML; ProgramError with every reason the net is not an SFC.

    `compile_file` (program/compiler.py's, which this room may not import) compiles the net's
    source again: when that is a PLCopen chart that compiles to this very net (the same
    program hash), the chart itself is written back (writechart.py: every action, the
    drawing); otherwise the net is inferred as a chart, or refused with the reasons."""
    stale: list[Problem] = []
    if compile_file is not None and is_plcopen(net.source):
        text, why = _from_chart(net, compile_file)
        if text is not None:
            return text
        stale.append(Problem(net.source.partition("#")[0], 1, "", why))
    problems = _reasons(net)
    if problems:
        raise ProgramError(stale + problems)
    return _Writer(net, layout(net)).text()


def _from_chart(net: CompiledNet,
                compile_file: Callable[[str], CompiledNet]) -> tuple[str | None, str]:
    """The chart the net was compiled from, written back; else None and why not."""
    name, _, pou = net.source.partition("#")
    pou = pou or net.name  # a chart's net is named after its POU (one file, several POUs)
    try:
        data = Path(name).read_bytes()
        again = compile_file(f"{name}#{pou}")
        chart = read_chart(data, name, pou)
    except OSError as exc:
        return None, f"cannot read the chart again: {exc.strerror}"
    except ProgramError as exc:
        return None, f"the chart no longer compiles ({exc.problems[0].message})"
    if again.program_hash != net.program_hash or Path(name).read_bytes() != data:
        return None, "the chart in this file compiles to another net than the one exported " \
            "(edited since it was compiled?): the net alone is exported"
    try:
        return write_chart(chart, data), ""
    except NotWritten as exc:  # the chart itself is refused: no inference of its net either
        raise ProgramError([Problem(name, exc.line, "", exc.message)]) from None


def layout(net: CompiledNet) -> dict[str, tuple[float, float]]:
    """Step and transition name -> `<position>` as drawn, when the net's source is the
    PLCopen chart it was compiled from (the net keeps no drawing); {} otherwise."""
    name, _, pou = net.source.partition("#")
    if not is_plcopen(name):
        return {}
    try:
        chart = read_chart(Path(name).read_bytes(), name, pou or None)
    except (OSError, ProgramError):
        return {}
    out = {s.name: (s.x, s.y) for s in chart.steps}
    out.update({t.name: t.xy for t in chart.transitions if t.xy is not None})
    return out


def _pos(xy: tuple[float, float], dx: float = 0, dy: float = 0) -> str:
    x, y = xy[0] + dx, xy[1] + dy
    return f'<position x="{x:g}" y="{y:g}"/>'


def _where(net: CompiledNet, t: Transition | None, place: int = 0) -> tuple[str, int]:
    if t is not None:
        return net.transition_where[t.index] if net.transition_where else (net.source, 0)
    return net.place_where[place] if net.place_where else (net.source, 0)


def _reasons(net: CompiledNet) -> list[Problem]:
    out: list[Problem] = []

    def say(where: tuple[str, int], message: str) -> None:
        out.append(Problem(where[0], where[1], "", f"not an SFC: {message}"))

    for i, name in enumerate(net.place_names):
        if net.coloured[i]:
            say(_where(net, None, i), f"place {name} holds coloured tokens (a step holds no data)")
        if net.initial[i] > 1:
            say(_where(net, None, i), f"place {name} starts with {net.initial[i]} tokens "
                "(a step is active or not)")
        for symbol, value in net.place_outputs.get(i, ()):
            if net.io.symbols[symbol].type.value != "bool" or value != 1:
                say(_where(net, None, i), f"place {name} drives {symbol} = {value} (an N "
                    "action makes a BOOL true)")
    if not any(net.initial):
        say((net.source, 1), "no place starts marked (a chart needs an initial step)")
    for t in net.transitions:
        w = _where(net, t)
        if not t.pre or not t.post:
            say(w, f"transition {t.name} has no {'input' if not t.pre else 'output'} place "
                "(a transition goes from steps to steps)")
        if any(a.weight != 1 for a in t.pre) or any(a.weight != 1 for a in t.post) or \
                any(w != 1 for _, w in (*t.test, *t.inhibit)):
            say(w, f"transition {t.name} has an arc of weight > 1")
        if t.duration_ns:
            say(w, f"transition {t.name} has a duration (an SFC transition clears at once)")
        if t.actions:
            say(w, f"transition {t.name} has actions (do:); a chart keeps actions on steps")
        if t.delay_ns and (t.guard is not None or len(t.pre) != 1 or t.delay_ns % 1_000_000):
            say(w, f"transition {t.name}: a delay is a step timer `Step.T >= T#..ms` only "
                "alone, after one step, in whole milliseconds")
        if t.guard is not None:
            events = set(net.io.events) | {"first_scan"}
            try:
                st_of(t.guard.text)
                if t.guard.edges or t.guard.reads & events:
                    raise _NotSt("an edge or an event")
            except (_NotSt, SyntaxError) as exc:
                say(w, f"transition {t.name}: guard {t.guard.text!r} has {exc} outside the "
                    "ST subset")
    for name, sym in net.io.symbols.items():
        if sym.scaling is not None:
            say((net.io.path, sym.line), f"symbol {name} is scaled (engineering units)")
    return out


class _Writer:
    def __init__(self, net: CompiledNet, drawn: dict[str, tuple[float, float]]) -> None:
        self.net, self.out = net, list[str]()
        self.xy = {p: drawn.get(p, (100.0, 60.0 * i)) for i, p in enumerate(net.place_names)}
        self.xy |= {t.name: drawn.get(t.name, (100.0 + 40 * net.rank[t.index], 0.0))
                    for t in net.transitions}
        self.ids = iter(range(1, 1 << 30))
        self.step_id = {p: next(self.ids) for p in net.place_names}
        self.t_id = {t.name: next(self.ids) for t in net.transitions}

    def names(self, arcs: tuple[InputArc, ...] | tuple[OutputArc, ...]) -> list[str]:
        return [self.net.place_names[a.place] for a in arcs]

    def text(self) -> str:
        net, rank = self.net, self.net.rank
        exits: dict[str, list[Transition]] = {}
        entries: dict[str, list[Transition]] = {}
        for t in net.transitions:
            if len(t.pre) == 1:
                exits.setdefault(self.names(t.pre)[0], []).append(t)
            if len(t.post) == 1:
                entries.setdefault(self.names(t.post)[0], []).append(t)
        div = {p: next(self.ids) for p, ts in exits.items() if len(ts) > 1}
        for p, d in div.items():
            self.out.append(f'<selectionDivergence localId="{d}">{_pos(self.xy[p], dy=40)}'
                            f'{self.pin(self.step_id[p])}'
                            '</selectionDivergence>')
        for i, p in enumerate(net.place_names):
            self.step(i, p, entries.get(p, []))
        for t in net.transitions:
            self.transition(t, rank[t.index], div)
        return self.project()

    def pin(self, *refs: int) -> str:
        return "".join(f'<connectionPointIn><connection refLocalId="{r}"/></connectionPointIn>'
                       for r in refs)

    def step(self, i: int, p: str, inputs: list[Transition]) -> None:
        ref = ""
        if len(inputs) == 1:
            ref = self.pin(self.t_id[inputs[0].name])
        elif inputs:
            c = next(self.ids)
            self.out.append(f'<selectionConvergence localId="{c}">{_pos(self.xy[p], dy=-20)}'
                            f'{self.pin(*(self.t_id[t.name] for t in inputs))}'
                            '</selectionConvergence>')
            ref = self.pin(c)
        initial = "true" if self.net.initial[i] else "false"
        self.out.append(f'<step localId="{self.step_id[p]}" name="{p}" initialStep="{initial}" '
                        f'height="30" width="90">{_pos(self.xy[p])}{ref}'
                        '<connectionPointOut formalParameter=""/>'
                        '<connectionPointOutAction formalParameter=""/></step>')
        outputs = self.net.place_outputs.get(i, ())
        if outputs:
            acts = "".join(f'<action localId="0"><reference name="{s}"/></action>'
                           for s, _ in outputs)
            self.out.append(f'<actionBlock localId="{next(self.ids)}" width="100" height="30">'
                            f'{_pos(self.xy[p], dx=150)}'
                            f'{self.pin(self.step_id[p])}{acts}</actionBlock>')

    def transition(self, t: Transition, rank: int, div: dict[str, int]) -> None:
        sources, targets = self.names(t.pre), self.names(t.post)
        if len(sources) == 1:
            pred = div.get(sources[0], self.step_id[sources[0]])
        else:
            pred = next(self.ids)
            self.out.append(f'<simultaneousConvergence localId="{pred}">'
                            f'{_pos(self.xy[t.name], dy=-20)}'
                            f'{self.pin(*(self.step_id[s] for s in sources))}'
                            '</simultaneousConvergence>')
        cond = [st_of(t.guard.text)] if t.guard is not None else []
        cond += [f"{self.net.place_names[p]}.X" for p, _ in t.test]
        cond += [f"NOT {self.net.place_names[p]}.X" for p, _ in t.inhibit]
        if t.delay_ns:
            cond = [f"{sources[0]}.T >= T#{t.delay_ns // 1_000_000}ms"]
        st = " AND ".join(cond) or "TRUE"
        tid = self.t_id[t.name]
        self.out.append(f'<transition localId="{tid}" priority="{rank}" height="2" width="20">'
                        f'{_pos(self.xy[t.name])}{self.pin(pred)}'
                        '<connectionPointOut/><condition><inline name=""><ST><xhtml:p>'
                        f'<![CDATA[{st}]]></xhtml:p></ST></inline></condition></transition>')
        if len(targets) > 1:
            d = next(self.ids)
            self.out.append(f'<simultaneousDivergence localId="{d}">'
                            f'{_pos(self.xy[t.name], dy=20)}{self.pin(tid)}'
                            '</simultaneousDivergence>')
            for k, s in enumerate(targets):
                self.out.append(f'<jumpStep localId="{next(self.ids)}" targetName="{s}">'
                                f'{_pos(self.xy[t.name], dx=60 * k, dy=40)}{self.pin(d)}'
                                '</jumpStep>')

    def project(self) -> str:
        sections: dict[str, list[str]] = {"inputVars": [], "outputVars": [], "localVars": []}
        for name, sym in self.net.io.symbols.items():
            address = str(sym.address)
            key = {"%I": "inputVars", "%Q": "outputVars"}.get(address[:2], "localVars")
            sections[key].append(f'<variable name="{name}" address={quoteattr(address)}>'
                                 f'<type><{_IEC[sym.type.value]}/></type></variable>')
        iface = "".join(f"<{k}>{''.join(v)}</{k}>" for k, v in sections.items() if v)
        body = "\n".join(self.out)
        return f"""<?xml version='1.0' encoding='utf-8'?>
<!-- Written by softplc from {self.net.source} (docs/sfc.md, export). -->
<project xmlns="http://www.plcopen.org/xml/tc6_0201" xmlns:xhtml="http://www.w3.org/1999/xhtml">
<fileHeader companyName="softplc" productName="softplc" productVersion="1"
 creationDateTime="1970-01-01T00:00:00"/>
<contentHeader name={quoteattr(self.net.name)}><coordinateInfo>
<fbd><scaling x="0" y="0"/></fbd><ld><scaling x="0" y="0"/></ld><sfc><scaling x="0" y="0"/></sfc>
</coordinateInfo></contentHeader>
<types><dataTypes/><pous><pou name={quoteattr(self.net.name)} pouType="program">
<interface>{iface}</interface>
<body><SFC>
{body}
</SFC></body></pou></pous></types>
<instances><configurations/></instances>
</project>
"""
