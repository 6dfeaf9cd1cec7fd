"""Generated charts whose conditions are wired from FBD/LD networks (hypothesis): a ring of
three steps, each condition a random network of the subset docs/sfc.md lists (AND, OR, XOR,
NOT, comparisons, SEL, contacts in series and parallel on a left power rail, negated pins,
contacts, outputs and conditions, connectors, TON/TOF/TP/R_TRIG/F_TRIG instances, each
called by one block) drawn in the SFC body or in a named transition's FBD/LD body."""

from __future__ import annotations

from typing import Any

from hypothesis import strategies as st

BOOLS = [f"i{k}" for k in range(4)]
INTS = ["n0", "n1"]
FBS = {"T0": "TON", "O0": "TOF", "P0": "TP", "R0": "R_TRIG", "G0": "F_TRIG"}
STEPS = ["S0", "S1", "S2"]


def _neg(data: st.DataObject) -> str:
    return ' negated="true"' if data.draw(st.integers(0, 4)) == 0 else ""


class _Net:
    def __init__(self, data: st.DataObject) -> None:
        self.data, self.next = data, 100
        self.objs: list[str] = []
        self.free = list(FBS)  # instances not yet called

    def new(self) -> int:
        self.next += 1
        return self.next

    def link(self, lid: int, param: str = "") -> str:
        formal = f' formalParameter="{param}"' if param else ""
        return f'<connection refLocalId="{lid}"{formal}/>'

    def var(self, text: str, boolean: bool = True) -> str:
        lid = self.new()
        neg = _neg(self.data) if boolean else ""
        self.objs.append(f'<inVariable localId="{lid}"{neg}><connectionPointOut/>'
                         f'<expression>{text}</expression></inVariable>')
        return self.link(lid)

    def block(self, typ: str, inputs: list[tuple[str, str]], out: str = "OUT",
              inst: str = "") -> str:
        lid = self.new()
        numeric = typ in ("GT", "GE", "LT", "LE", "EQ", "NE")
        ins = "".join(f'<variable formalParameter="{p}"'
                      f'{_neg(self.data) if p != "PT" and not numeric else ""}>'
                      f'<connectionPointIn>{w}</connectionPointIn></variable>'
                      for p, w in inputs)
        name = f' instanceName="{inst}"' if inst else ""
        self.objs.append(f'<block localId="{lid}" typeName="{typ}"{name}><inputVariables>{ins}'
                         f'</inputVariables><inOutVariables/><outputVariables><variable '
                         f'formalParameter="{out}"{_neg(self.data)}><connectionPointOut/>'
                         '</variable></outputVariables></block>')
        return self.link(lid, out)

    def contacts(self) -> str:
        """One or two branches of one or two contacts from a left power rail: the wires."""
        rail = self.new()
        self.objs.append(f'<leftPowerRail localId="{rail}"><connectionPointOut '
                         'formalParameter=""/></leftPowerRail>')
        ends = []
        for _ in range(self.data.draw(st.integers(1, 2))):
            wire = self.link(rail)
            for _ in range(self.data.draw(st.integers(1, 2))):
                lid = self.new()
                self.objs.append(f'<contact localId="{lid}"{_neg(self.data)}><connectionPointIn>'
                                 f'{wire}</connectionPointIn><connectionPointOut/><variable>'
                                 f'{self.data.draw(st.sampled_from(BOOLS))}</variable>'
                                 '</contact>')
                wire = self.link(lid)
            ends.append(wire)
        return "".join(ends)

    def number(self) -> str:
        return self.var(self.data.draw(st.sampled_from([*INTS, "3", "7"])), boolean=False)

    def boolean(self, depth: int) -> str:
        kinds = ["var", "var", "contacts"] + (["logic", "not", "cmp", "sel", "fb"] if depth
                                              else [])
        kind = self.data.draw(st.sampled_from(kinds))
        if kind == "fb" and not self.free:
            kind = "var"
        if kind == "var":
            return self.var(self.data.draw(st.sampled_from(BOOLS)))
        if kind == "contacts":
            return self.contacts()
        if kind == "logic":
            typ = self.data.draw(st.sampled_from(["AND", "OR", "XOR"]))
            n = self.data.draw(st.integers(2, 3))
            return self.block(typ, [(f"IN{k + 1}", self.boolean(depth - 1)) for k in range(n)])
        if kind == "not":
            return self.block("NOT", [("IN", self.boolean(depth - 1))])
        if kind == "cmp":
            typ = self.data.draw(st.sampled_from(["GT", "GE", "LT", "LE", "EQ", "NE"]))
            n = 2 if typ == "NE" else self.data.draw(st.integers(2, 3))
            return self.block(typ, [(f"IN{k + 1}", self.number()) for k in range(n)])
        if kind == "sel":
            return self.block("SEL", [("G", self.boolean(depth - 1)),
                                      ("IN0", self.boolean(depth - 1)),
                                      ("IN1", self.boolean(depth - 1))])
        inst = self.data.draw(st.sampled_from(self.free))
        self.free.remove(inst)
        typ = FBS[inst]
        if typ in ("R_TRIG", "F_TRIG"):
            return self.block(typ, [("CLK", self.boolean(depth - 1))], "Q", inst)
        pt = self.new()
        self.objs.append(f'<inVariable localId="{pt}"><connectionPointOut/><expression>'
                         f'T#{self.data.draw(st.sampled_from([20, 30, 50]))}ms</expression>'
                         '</inVariable>')
        return self.block(typ, [("IN", self.boolean(depth - 1)), ("PT", self.link(pt))],
                          "Q", inst)


def fbd_chart(data: st.DataObject) -> str:
    """The XML text of one generated chart."""
    net = _Net(data)
    sfc, named = [], []
    for k, step in enumerate(STEPS):
        prev = 10 + 2 * ((k - 1) % 3) + 1  # the transition entering this step
        sfc.append(f'<step localId="{10 + 2 * k}" name="{step}" initialStep='
                   f'"{str(k == 0).lower()}"><connectionPointIn>{net.link(prev)}'
                   '</connectionPointIn><connectionPointOut/></step>')
        sfc.append(f'<actionBlock localId="{50 + k}"><connectionPointIn>{net.link(10 + 2 * k)}'
                   f'</connectionPointIn><action localId="0" qualifier="N"><reference '
                   f'name="q{k}"/></action></actionBlock>')
        negated = ' negated="true"' if data.draw(st.integers(0, 5)) == 0 else ""
        if data.draw(st.integers(0, 3)) == 0:  # a named transition with an FBD/LD body
            body = _Net(data)
            body.free, body.next = net.free, net.next + 1000
            wire = body.boolean(2)
            net.free = body.free
            lid = body.new()
            ld = body.objs[-1].startswith("<contact")  # LD: a coil after the contacts
            end = (f'<coil localId="{lid}"><connectionPointIn>{wire}</connectionPointIn>'
                   f'<connectionPointOut/><variable>TR{k}</variable></coil>') if ld else \
                (f'<outVariable localId="{lid}"><connectionPointIn>{wire}</connectionPointIn>'
                 f'<expression>TR{k}</expression></outVariable>')
            tag = "LD" if ld else "FBD"
            named.append(f'<transition name="TR{k}"><body><{tag}>{"".join(body.objs)}{end}'
                         f'</{tag}></body></transition>')
            cond = f'<condition{negated}><reference name="TR{k}"/></condition>'
        else:
            cond = f'<condition{negated}><connectionPointIn>{net.boolean(3)}' \
                '</connectionPointIn></condition>'
        sfc.append(f'<transition localId="{11 + 2 * k}"><connectionPointIn>'
                   f'{net.link(10 + 2 * k)}</connectionPointIn><connectionPointOut/>{cond}'
                   '</transition>')
    return _project(sfc + net.objs, named)


def _project(sfc: list[str], named: list[str]) -> str:
    def var(name: str, typ: str, address: str = "") -> str:
        at = f' address="{address}"' if address else ""
        return f'<variable name="{name}"{at}><type>{typ}</type></variable>'

    interface = "".join([*(var(b, "<BOOL/>", f"%IX0.{k}") for k, b in enumerate(BOOLS)),
                         *(var(n, "<INT/>", f"%IW{k}") for k, n in enumerate(INTS)),
                         *(var(f"q{k}", "<BOOL/>", f"%QX0.{k}") for k in range(3)),
                         *(var(i, f'<derived name="{t}"/>') for i, t in FBS.items())])
    transitions = f"<transitions>{''.join(named)}</transitions>" if named else ""
    return ('<?xml version="1.0" encoding="utf-8"?>\n<project xmlns='
            '"http://www.plcopen.org/xml/tc6_0201" xmlns:xhtml="http://www.w3.org/1999/xhtml">'
            '<types><dataTypes/><pous><pou name="Gen" pouType="program"><interface><localVars>'
            f'{interface}</localVars></interface>{transitions}<body><SFC>\n'
            + "\n".join(sfc) + '\n</SFC></body></pou></pous></types></project>\n')


def fbd_inputs(data: st.DataObject, scans: int) -> list[dict[str, Any]]:
    kinds: dict[str, Any] = {b: st.booleans() for b in BOOLS} | \
        {n: st.integers(0, 9) for n in INTS}
    return data.draw(st.lists(st.fixed_dictionaries(kinds), min_size=scans, max_size=scans))
