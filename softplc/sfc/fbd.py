"""FBD blocks and LD contacts wired into a transition condition -> ST text (docs/sfc.md).

Owns: walking a network backwards from the pin a condition (or a named transition's
outVariable/coil) reads: inVariables (their ST expression), the functions AND, OR, XOR,
NOT, GT, GE, LT, LE, EQ, NE, SEL as the equivalent ST expression, TON/TOF/TP/R_TRIG/F_TRIG
instances as `T1.Q` plus their call `T1(IN := ..., PT := ...);`, which runs every scan
(Beremiz's hidden COMPUTE_FUNCTION_BLOCKS action; the calls come out inputs first), a left
power rail as TRUE, contacts in series (AND) and parallel (several connections: OR),
negated pins and contacts, connectors/continuations; and the located refusal of anything
else (another block, an edge or a stored pin, a loop, a dangling input).
Does not know: ST parsing (the reader parses what this writes), nets, YAML.
"""

from __future__ import annotations

from collections.abc import Iterable
from itertools import pairwise

from softplc.core.errors import SoftplcError
from softplc.core.xmltree import Node
from softplc.sfc import fbs

LOGIC = {"AND": "AND", "OR": "OR", "XOR": "XOR"}
COMPARE = {"GT": ">", "GE": ">=", "LT": "<", "LE": "<=", "EQ": "=", "NE": "<>"}
SUPPORTED = ("supported in a wired condition: inVariables, the functions AND, OR, XOR, NOT, "
             "GT, GE, LT, LE, EQ, NE, SEL, instances of "
             f"{', '.join((*fbs.TIMERS, *fbs.TRIGGERS))} (output Q), LD left power rails, "
             "contacts (series, parallel, negated), coils, connectors")
EVERY_SCAN = "COMPUTE_FUNCTION_BLOCKS"  # Beremiz's name for the hidden every-scan action


class FbdError(SoftplcError, ValueError):
    """A network outside the subset: the reader turns it into a located problem."""

    def __init__(self, line: int, message: str) -> None:
        super().__init__(line, message)
        self.line, self.message = line, message


def _true(node: Node, attr: str) -> bool:
    return node.attrs.get(attr, "false").lower() in ("true", "1")


def _not(text: str, negated: bool) -> str:
    return f"NOT ({text})" if negated else text


def _desc(node: Node) -> str:
    kind = node.attrs.get("typeName", "")
    inst = node.attrs.get("instanceName", "")
    what = f"{node.tag} {kind}{f' {inst}' if inst else ''}".strip()
    return f"{what} (localId {node.attrs.get('localId', '?')})"


class Network:
    """The objects of one body (an SFC body, or a named transition's FBD/LD body); `calls`
    collects the function block calls every condition read from it needs, inputs first."""

    def __init__(self, objects: Iterable[Node], names: dict[str, tuple[str, str]]) -> None:
        self.objs = {n.attrs["localId"]: n for n in objects if "localId" in n.attrs}
        self.names = names
        self.done: dict[str, bool] = {}  # block localId -> called (True) / being walked
        self.calls: list[tuple[str, int, str]] = []  # (ST call, the block's line, the block)

    def pin(self, pin: Node, what: str, line: int) -> str:
        """The ST value on an input pin (a connectionPointIn or its owner)."""
        links = [c for c in pin.all("connection")]
        if not links:
            raise FbdError(line, f"{what} is not connected (a dangling input); every input of "
                           "a network wired into a condition must be wired")
        texts = [self._source(c, what, line) for c in links]
        return texts[0] if len(texts) == 1 else "(" + " OR ".join(texts) + ")"

    def _source(self, link: Node, what: str, line: int) -> str:
        ref = link.attrs.get("refLocalId", "")
        node = self.objs.get(ref)
        if node is None:
            raise FbdError(line, f"{what} is wired to localId {ref!r}, which is not in this "
                           "body")
        tag = node.tag
        if tag == "inVariable":
            expr = node.child("expression")
            text = expr.all_text().strip() if expr is not None else ""
            if not text:
                raise FbdError(node.line, f"{_desc(node)} has no expression")
            return _not(f"({text})", _true(node, "negated"))
        if tag == "leftPowerRail":
            return "TRUE"
        if tag == "contact":
            return self._contact(node)
        if tag == "coil":
            if node.attrs.get("storage", "none") not in ("", "none") or \
                    node.attrs.get("edge", "none") not in ("", "none"):
                raise FbdError(node.line, f"{_desc(node)}: a set/reset or edge coil inside a "
                               f"condition's network is not supported ({SUPPORTED})")
            return self._inner(node, "the coil's input")
        if tag == "continuation":
            return self._continuation(node)
        if tag == "block":
            return self._block(node, link.attrs.get("formalParameter", ""))
        raise FbdError(node.line, f"{what} is wired from {_desc(node)}: {SUPPORTED}")

    def _inner(self, node: Node, what: str) -> str:
        lid = node.attrs["localId"]
        if self.done.get(lid) is False:
            raise FbdError(node.line, f"{_desc(node)} is in a loop: a network wired into a "
                           "condition must not feed back into itself")
        self.done[lid] = False
        pin = node.child("connectionPointIn")
        text = self.pin(pin if pin is not None else node, f"{what} of {_desc(node)}",
                        node.line)
        del self.done[lid]
        return text

    def _contact(self, node: Node) -> str:
        if node.attrs.get("edge", "none") not in ("", "none"):
            raise FbdError(node.line, f"{_desc(node)}: an edge contact (rising/falling) is not "
                           "supported: use an R_TRIG/F_TRIG block")
        var = node.child("variable")
        name = var.all_text().strip() if var is not None else ""
        if not name:
            raise FbdError(node.line, f"{_desc(node)} names no variable")
        power = self._inner(node, "the input")
        own = _not(name, _true(node, "negated"))
        return own if power == "TRUE" else f"({power} AND {own})"

    def _continuation(self, node: Node) -> str:
        name = node.attrs.get("name", "").upper()
        found = [n for n in self.objs.values() if n.tag == "connector"
                 and n.attrs.get("name", "").upper() == name]
        if len(found) != 1:
            raise FbdError(node.line, f"continuation {name!r}: {len(found)} connectors of that "
                           "name in this body (expected one)")
        return self._inner(found[0], "the input")

    def _block(self, node: Node, output: str) -> str:
        typ = node.attrs.get("typeName", "").upper()
        inst = node.attrs.get("instanceName", "")
        if inst and typ in (*fbs.TIMERS, *fbs.TRIGGERS):
            return self._instance(node, typ, inst, output)
        if typ not in (*LOGIC, *COMPARE, "NOT", "SEL") or inst:
            raise FbdError(node.line, f"{_desc(node)} is outside the subset; {SUPPORTED}")
        lid = node.attrs["localId"]
        if self.done.get(lid) is False:
            raise FbdError(node.line, f"{_desc(node)} is in a loop: a network wired into a "
                           "condition must not feed back into itself")
        self.done[lid] = False
        args = self._inputs(node)
        del self.done[lid]
        return _not(self._function(node, typ, args), self._out_negated(node, output))

    def _inputs(self, node: Node) -> list[tuple[str, str]]:
        out = []
        ins = node.child("inputVariables")
        for var in ins.all("variable") if ins is not None else []:
            param = var.attrs.get("formalParameter", "")
            what = f"input {param} of {_desc(node)}"
            if var.attrs.get("edge", "none") not in ("", "none"):
                raise FbdError(node.line, f"{what}: an edge input (rising/falling) is not "
                               "supported: use an R_TRIG/F_TRIG block")
            pin = var.child("connectionPointIn")
            if param.upper() == "EN":
                if pin is not None and pin.all("connection"):
                    raise FbdError(node.line, f"{what}: EN/ENO are not supported")
                continue
            text = self.pin(pin if pin is not None else var, what, node.line)
            out.append((param.upper(), _not(text, _true(var, "negated"))))
        return out

    @staticmethod
    def _function(node: Node, typ: str, args: list[tuple[str, str]]) -> str:
        values = [text for _, text in args]
        want = {"NOT": 1, "SEL": 3, "NE": 2}.get(typ)
        if (want is not None and len(values) != want) or (want is None and len(values) < 2):
            raise FbdError(node.line, f"{_desc(node)}: {typ} takes "
                           f"{want or 'two or more'} inputs, the block has {len(values)}")
        if typ == "NOT":
            return f"NOT ({values[0]})"
        if typ == "SEL":
            by = dict(args)
            if set(by) != {"G", "IN0", "IN1"}:
                raise FbdError(node.line, f"{_desc(node)}: SEL's inputs are G, IN0, IN1")
            return f"SEL({by['G']}, {by['IN0']}, {by['IN1']})"
        if typ in LOGIC:
            return "(" + f" {LOGIC[typ]} ".join(values) + ")"
        pairs = [f"({a} {COMPARE[typ]} {b})" for a, b in pairwise(values)]
        return pairs[0] if len(pairs) == 1 else "(" + " AND ".join(pairs) + ")"

    @staticmethod
    def _out_negated(node: Node, output: str) -> bool:
        outs = node.child("outputVariables")
        found = [v for v in (outs.all("variable") if outs is not None else [])
                 if not output or v.attrs.get("formalParameter", "").upper() == output.upper()]
        return bool(found) and _true(found[0], "negated")

    def _instance(self, node: Node, typ: str, inst: str, output: str) -> str:
        declared = self.names.get(inst.upper())
        if declared is None or declared[1] != f"fb:{typ}":
            got = "not declared" if declared is None else \
                f"declared as {declared[1].removeprefix('fb:').upper()}"
            raise FbdError(node.line, f"{_desc(node)}: the instance {inst} is {got}; declare "
                           f"`{inst} : {typ}` in the POU's interface")
        if (output or "Q").upper() != "Q":
            raise FbdError(node.line, f"{_desc(node)}: output {output} read; only Q is ("
                           f"{fbs.SUPPORTED}; ET needs a clock softplc's expressions do not "
                           "read)")
        lid = node.attrs["localId"]
        if self.done.get(lid) is False:
            raise FbdError(node.line, f"{_desc(node)} is in a loop: a network wired into a "
                           "condition must not feed back into itself")
        if lid not in self.done:
            self.done[lid] = False
            args = self._inputs(node)
            self.done[lid] = True
            text = ", ".join(f"{p} := {v}" for p, v in args)
            self.calls.append((f"{inst}({text});", node.line, _desc(node)))
        return _not(f"{inst}.Q", self._out_negated(node, "Q"))


def named_output(body: Node, name: str) -> Node | None:
    """The outVariable or coil of an FBD/LD named transition's body that carries its value."""
    for node in body.walk():
        if node.tag == "outVariable":
            expr = node.child("expression")
            if expr is not None and expr.all_text().strip().upper() == name.upper():
                return node
        if node.tag == "coil":
            var = node.child("variable")
            if var is not None and var.all_text().strip().upper() == name.upper():
                return node
    return None
