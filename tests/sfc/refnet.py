"""The reference interpreter's FBD/LD networks (refsfc.py uses it), from the XML and the
standard, independent of softplc/sfc/fbd.py: a condition wired from a network is the value on
its pin, computed object by object (IEC 61131-3 Ed.3 Tables 22-27 for the functions, 8.2 for
LD: a contact passes power AND its variable, wires joined at a pin are an OR); function block
instances in the SFC body are called every scan, as Beremiz's COMPUTE_FUNCTION_BLOCKS action
(stored on the initial step) does, each once per scan, every input wired before it is read.

The choices docs/sfc.md states and this interpreter shares: a function (AND, GT ...) is
evaluated when the condition is (not one scan earlier into a temporary as Beremiz's generated
code does); the blocks run first in the scan's action phase, reading the variables as the
previous scan left them (before this scan's actions write).
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import pairwise
from typing import Any

CHAINS: dict[str, Callable[[Any, Any], bool]] = {
    "GT": lambda a, b: a > b, "GE": lambda a, b: a >= b, "LT": lambda a, b: a < b,
    "LE": lambda a, b: a <= b, "EQ": lambda a, b: a == b}
FUNCS: dict[str, Callable[[list[Any]], Any]] = {
    "AND": all, "OR": any, "XOR": lambda v: sum(map(bool, v)) % 2 == 1,
    "NOT": lambda v: not v[0], "SEL": lambda v: v[2] if v[0] else v[1],
    "NE": lambda v: v[0] != v[1],
    **{k: (lambda test: lambda v: all(test(a, b) for a, b in pairwise(v)))(f)
       for k, f in CHAINS.items()},
}


def local(tag: str) -> str:
    return tag.rpartition("}")[2]


def kids(node: Any, tag: str) -> list[Any]:
    return [c for c in node if local(c.tag) == tag]


def _links(node: Any) -> list[Any]:
    """The connections into an object's (or a pin's) input."""
    pins = [node] if local(node.tag) in ("connectionPointIn", "condition") else \
        kids(node, "connectionPointIn")
    return [c for p in pins for c in kids(p, "connection")]


def _neg(node: Any) -> bool:
    return str(node.get("negated")) == "true"


class RefNet:
    """The objects of one body; `evaluate` reads wires, `calls` are the FB blocks in order."""

    def __init__(self, body: Any, evaluate: Callable[[str, dict[str, Any]], Any]) -> None:
        self.objs = {o.get("localId"): o for o in body if o.get("localId")}
        self.expr = evaluate  # ST text -> value (the interpreter's own evaluator)
        self.calls: list[Any] = []  # FB blocks the conditions read, every input first

    def wire(self, pin: Any) -> Callable[[dict[str, Any], dict[str, Any]], Any]:
        """The condition on a pin: (env, fbs) -> value; registers the FB blocks it needs."""
        for link in _links(pin):
            self._register(link.get("refLocalId"))
        return lambda env, fbs: self._pin(pin, env, fbs)

    def _register(self, lid: str) -> None:
        o = self.objs[lid]
        for link in [c for v in o.iter() if local(v.tag) == "connectionPointIn"
                     for c in kids(v, "connection")]:
            self._register(link.get("refLocalId"))
        if local(o.tag) == "continuation":
            self._register(self._connector(o).get("localId"))
        if local(o.tag) == "block" and o.get("instanceName") and o not in self.calls:
            self.calls.append(o)

    def _connector(self, o: Any) -> Any:
        return next(c for c in self.objs.values() if local(c.tag) == "connector"
                    and c.get("name", "").upper() == o.get("name", "").upper())

    def _pin(self, pin: Any, env: dict[str, Any], fbs: dict[str, Any]) -> Any:
        values = [self._out(c.get("refLocalId"), c.get("formalParameter"), env, fbs)
                  for c in _links(pin)]
        return values[0] if len(values) == 1 else any(values)

    def _out(self, lid: str, param: str | None, env: dict[str, Any],
             fbs: dict[str, Any]) -> Any:
        o = self.objs[lid]
        tag = local(o.tag)
        if tag == "inVariable":
            value = self.expr("".join(kids(o, "expression")[0].itertext()), env)
            return (not value) if _neg(o) else value
        if tag == "leftPowerRail":
            return True
        if tag == "contact":
            name = "".join(kids(o, "variable")[0].itertext()).strip().upper()
            var = next(v for k, v in env.items() if k.upper() == name)
            return bool(self._pin(o, env, fbs)) and (not var if _neg(o) else bool(var))
        if tag == "coil":
            return self._pin(o, env, fbs)
        if tag == "continuation":
            return self._pin(self._connector(o), env, fbs)
        outs = kids(kids(o, "outputVariables")[0], "variable")
        out = next((v for v in outs if v.get("formalParameter") == param), outs[0])
        if o.get("instanceName"):
            value = fbs[o.get("instanceName").upper()].q
        else:
            value = FUNCS[o.get("typeName").upper()](
                [v for _, v in self.inputs(o, env, fbs)])
        return (not value) if _neg(out) else value

    def inputs(self, o: Any, env: dict[str, Any], fbs: dict[str, Any]) -> list[tuple[str, Any]]:
        out = []
        for var in kids(kids(o, "inputVariables")[0], "variable"):
            value = self._pin(kids(var, "connectionPointIn")[0], env, fbs)
            out.append((var.get("formalParameter").upper(), (not value) if _neg(var) else value))
        return out

    def run_blocks(self, env: dict[str, Any], fbs: dict[str, Any], cur: int) -> None:
        """Every FB block once, inputs first (the COMPUTE_FUNCTION_BLOCKS action)."""
        for o in self.calls:
            env_q = env | {f"{n}.Q": fb.q for n, fb in fbs.items()}
            fbs[o.get("instanceName").upper()].call(dict(self.inputs(o, env_q, fbs)), cur)
