"""A reference SFC interpreter written from IEC 61131-3 (Ed.2 2.6, Ed.3 6.7), independent of
softplc/sfc: it reads the PLCopen XML itself and runs the evolution rules directly, scan by
scan, for comparison with the net the chart compiles to.

Rules it implements (docs/sfc.md states the same choices for the net):
- initial steps active at start; a transition is enabled when all its preceding steps are
  active, clears when also its condition is true; clearable transitions clear together, a
  selection divergence's branches walked left to right (XML priority, then position x, then
  document order): a cleared transition deactivates its preceding steps at once, so a later
  sibling finds them inactive;
- conditions see the step activity and the variables at the start of the scan; Step.T is the
  time since the first scan the step was active in;
- after the clearing: N on a BOOL: true while a step holding it is active; S/R on entry (R
  overrides); P/P1 on entry and P0 on exit pulse a BOOL for one scan; an N action with an ST
  body runs in every scan its step is active and once more in the scan it is left (IEC's
  final execution, Q falling); P1/P0 bodies run once on entry/exit;
- timed actions on a BOOL, each its own ACTION_CONTROL timer started with the step (on the
  same clock as Step.T): L true while the step is active and its time is below the duration,
  D true while it is active and its time has reached it, DS stored (until an R) once the
  step has been active for the duration; evaluated after the clearing, before S and R (R
  overrides the stored DS);
- SD and SL on a BOOL, ACTION_CONTROL's latch and timer (Ed.2 2.6.4.5, figure 15): the latch
  SD_FF/SL_FF is set while the step is active and held reset while a step with an R of the
  same BOOL is active (R dominant); a TON runs on the latch (from the first scan the latch is
  set at the start of the scan, the Step.T clock), not on the step: SD is the TON's Q, SL the
  latch AND NOT Q. A new activation while latched changes nothing; only an R ends it;
- standard function blocks (RefFb): TON, TOF, TP as the IEC bodies matiec writes (a STATE
  machine per instance, Q changed only by a call), R_TRIG/F_TRIG as IEC's two lines; an
  instance runs when a body calling it runs (`T1(IN := x, PT := T#5s);`, formal arguments,
  a missing input keeps its last value) and `T1.Q` reads its output (a body reads Step.X
  after the clearing: FALSE in an N body's final execution). The timers read the
  scan clock docs/sfc.md states: START_TIME is the time of the scan after the starting call,
  and a call's CURRENT_TIME is the time of the scan before its own.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import defusedxml.ElementTree as ET  # type: ignore[import-untyped]

from tests.sfc.refnet import RefNet


def _local(tag: str) -> str:
    return tag.rpartition("}")[2]


def _kids(node: Any, tag: str) -> list[Any]:
    return [c for c in node if _local(c.tag) == tag]


def _text(node: Any) -> str:
    return "".join(node.itertext())


@dataclass
class RefTransition:
    sources: list[str]
    targets: list[str]
    condition: str | Callable[[dict[str, Any], dict[str, Any]], Any]  # ST, or a network
    key: tuple[int, float, int]


@dataclass
class RefChart:
    steps: list[str]
    initial: set[str]
    transitions: list[RefTransition]
    actions: list[tuple[str, str, str]]  # step, qualifier, name
    bodies: dict[str, str]
    types: dict[str, str] = field(default_factory=dict)
    durations: dict[tuple[str, str], int] = field(default_factory=dict)  # (step, name) -> ms
    nets: list[RefNet] = field(default_factory=list)  # FBD/LD networks wired into conditions


def read(xml_text: str, pou_name: str | None = None) -> RefChart:
    root = ET.fromstring(xml_text)
    pous = [p for p in root.iter() if _local(p.tag) == "pou"
            and any(_local(b.tag) == "SFC" for b in p.iter())]
    pou = next(p for p in pous if pou_name is None or p.get("name") == pou_name)
    sfc = next(b for b in pou.iter() if _local(b.tag) == "SFC")
    objs = {o.get("localId"): o for o in sfc if o.get("localId")}
    order = {lid: i for i, lid in enumerate(objs)}

    def ins(o: Any) -> list[str]:
        return [c.get("refLocalId") for pin in _kids(o, "connectionPointIn")
                for c in _kids(pin, "connection")]

    def back(lid: str) -> list[str]:
        o = objs[lid]
        if _local(o.tag) == "step":
            return [o.get("name")]
        return [s for p in ins(o) for s in back(p)]

    def ahead(lid: str) -> list[str]:
        out = []
        for o_id, o in objs.items():
            if lid in ins(o):
                tag = _local(o.tag)
                if tag == "step":
                    out.append(o.get("name"))
                elif tag == "jumpStep":
                    out.append(o.get("targetName"))
                elif tag.endswith(("Divergence", "Convergence")):
                    out.extend(ahead(o_id))
        return out

    transitions = []
    nets = [RefNet(sfc, lambda text, env: Eval(text, env).expr())]
    for lid, o in objs.items():
        if _local(o.tag) != "transition":
            continue
        text = _condition(_kids(o, "condition")[0], pou, objs, nets)
        pos = _kids(o, "position")
        x = float(pos[0].get("x", 0)) if pos else 0.0
        transitions.append(RefTransition(
            [s for p in ins(o) for s in back(p)], ahead(lid), text,
            (int(o.get("priority", 0)), x, order[lid])))
    steps = [o.get("name") for o in objs.values() if _local(o.tag) == "step"]
    initial = {o.get("name") for o in objs.values() if _local(o.tag) == "step"
               and o.get("initialStep") == "true"}
    actions: list[tuple[str, str, str]] = []
    durations: dict[tuple[str, str], int] = {}
    inline: dict[str, str] = {}
    for o in objs.values():
        if _local(o.tag) == "actionBlock":
            step = objs[ins(o)[0]].get("name")
            for a in _kids(o, "action"):
                if _kids(a, "inline"):
                    name = f"inline{len(inline)}"
                    inline[name] = _text(a)
                else:
                    name = _kids(a, "reference")[0].get("name")
                actions.append((step, a.get("qualifier") or "N", name))
                if a.get("duration"):
                    lit = a.get("duration")
                    durations[(step, name)] = _ms(lit if "#" in lit else f"T#{lit}")
    bodies = {a.get("name"): _text(a) for a in pou.iter() if _local(a.tag) == "action"
              and a.get("name")} | inline
    types = {v.get("name"): _type(next(iter(_kids(v, "type")[0])))
             for v in pou.iter() if _local(v.tag) == "variable" and _kids(v, "type")}
    return RefChart(steps, initial, transitions, actions, bodies, types, durations, nets)


def _type(node: Any) -> str:
    """BOOL, INT, ... or a derived type's name (TON, R_TRIG ...)."""
    return str(node.get("name")).upper() if _local(node.tag) == "derived" else _local(node.tag)


def _condition(cond: Any, pou: Any, objs: dict[str, Any], nets: list[RefNet]
               ) -> str | Callable[[dict[str, Any], dict[str, Any]], Any]:
    """Inline ST, a named transition's `:= expr;` body or FBD/LD network (its outVariable or
    coil named after it), a wired inVariable's expression, or a wired network."""
    negated = cond.get("negated") == "true"
    if _kids(cond, "inline"):
        text = _text(_kids(cond, "inline")[0])
    elif _kids(cond, "reference"):
        name = _kids(cond, "reference")[0].get("name")
        body = next(t for t in pou.iter() if _local(t.tag) == "transition"
                    and t.get("name") == name)
        graphic = [g for g in body.iter() if _local(g.tag) in ("FBD", "LD")]
        if graphic:
            out = next(o for o in graphic[0] if _local(o.tag) in ("outVariable", "coil") and
                       _text(o).strip().upper().endswith(name.upper()))
            nets.append(RefNet(graphic[0], nets[0].expr))
            return _negated(nets[-1].wire(_kids(out, "connectionPointIn")[0]), negated)
        text = _text(body).split(":=", 1)[-1].strip().rstrip(";")
    else:
        pins = _kids(cond, "connectionPointIn") or [cond]
        ref = _kids(pins[0], "connection")[0].get("refLocalId")
        if _local(objs[ref].tag) != "inVariable" or objs[ref].get("negated") == "true":
            return _negated(nets[0].wire(pins[0]), negated)
        text = _text(next(e for e in objs[ref] if _local(e.tag) == "expression"))
    return f"NOT ({text})" if negated else text


def _negated(wire: Callable[[dict[str, Any], dict[str, Any]], Any], negated: bool
             ) -> Callable[[dict[str, Any], dict[str, Any]], Any]:
    return (lambda env, fbs: not wire(env, fbs)) if negated else wire


# ---- a small ST evaluator (its own tokenizer and precedence climbing) ----

_TOK = re.compile(r"\s*(T#[0-9a-zA-Z_.]+|\d+\.\d+|\d+|:=|<>|<=|>=|[A-Za-z_][A-Za-z0-9_]*"
                  r"(?:\.[A-Za-z])?|[-+*/()<>=;,&])", re.IGNORECASE)
_PREC = {"OR": 1, "XOR": 2, "AND": 3, "&": 3, "=": 4, "<>": 4, "<": 5, ">": 5, "<=": 5,
         ">=": 5, "+": 6, "-": 6, "*": 7, "/": 7}


def _ms(lit: str) -> int:
    total = 0.0
    for num, unit in re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", lit.partition("#")[2].lower()):
        total += float(num) * {"ms": 1, "s": 1000, "m": 60000, "h": 3600000}[unit]
    return int(total)


class Eval:
    def __init__(self, text: str, env: dict[str, Any]) -> None:
        self.toks = [t for t in _TOK.findall(text) if t]
        self.i, self.env = 0, {k.upper(): v for k, v in env.items()}  # ST ignores case

    def peek(self) -> str:
        return self.toks[self.i].upper() if self.i < len(self.toks) else ""

    def expr(self, level: int = 1) -> Any:
        left = self.unary()
        while _PREC.get(self.peek(), 0) >= level:
            op = self.peek()
            self.i += 1
            right = self.expr(_PREC[op] + 1)
            left = _apply(op, left, right)
        return left

    def unary(self) -> Any:
        tok = self.peek()
        if tok == "NOT":
            self.i += 1
            return not self.unary()
        if tok == "-":
            self.i += 1
            return -self.unary()
        self.i += 1
        if tok == "(":
            value = self.expr()
            self.i += 1
            return value
        if tok in ("TRUE", "FALSE"):
            return tok == "TRUE"
        if tok.startswith("T#"):
            return _ms(tok)
        if tok[0].isdigit():
            return float(tok) if "." in tok else int(tok)
        if self.peek() == "(":
            self.i += 1
            args = [self.expr()]
            while self.peek() == ",":
                self.i += 1
                args.append(self.expr())
            self.i += 1
            funcs: dict[str, Callable[[list[Any]], Any]] = {
                "AND": all, "OR": any, "SEL": lambda a: a[2] if a[0] else a[1]}
            return funcs[tok](args)
        return self.env[tok]


def _apply(op: str, a: Any, b: Any) -> Any:
    if op in ("AND", "&"):
        return bool(a) and bool(b)
    if op == "OR":
        return bool(a) or bool(b)
    if op == "XOR":
        return bool(a) != bool(b)
    if op == "/":
        return int(a / b) if isinstance(a, int) and isinstance(b, int) else a / b
    return {"=": lambda: a == b, "<>": lambda: a != b, "<": lambda: a < b,
            ">": lambda: a > b, "<=": lambda: a <= b, ">=": lambda: a >= b,
            "+": lambda: a + b, "-": lambda: a - b, "*": lambda: a * b}[op]()


FB_TYPES = ("TON", "TOF", "TP", "R_TRIG", "F_TRIG")
_PENDING = -1  # START_TIME of a timer started in this scan: the next scan's time


class RefFb:
    """One function block instance, its body as in IEC 61131-3 (Ed.3 Table 43-44, the
    bistables and edges; the timers' STATE machines as matiec's standard_FB.txt writes them).
    `cur` is the time the call reads (the previous scan's), `start` a timer's START_TIME."""

    def __init__(self, typ: str) -> None:
        self.typ, self.state, self.q, self.m = typ, 0, False, False
        self.inp, self.prev_in, self.pt, self.start = False, False, 0, _PENDING

    def call(self, args: dict[str, Any], cur: int) -> None:
        if self.typ in ("R_TRIG", "F_TRIG"):
            clk = bool(args.get("CLK", self.m if self.typ == "R_TRIG" else not self.m))
            self.q = (clk and not self.m) if self.typ == "R_TRIG" else (not clk and not self.m)
            self.m = clk if self.typ == "R_TRIG" else not clk
            return
        self.inp, self.pt = bool(args.get("IN", self.inp)), args.get("PT", self.pt)
        inp = self.inp
        up = self.state == 0 and not self.prev_in and inp
        ran_out = self.start != _PENDING and self.start + self.pt <= cur
        if self.typ == "TON":
            if up:
                self.state, self.q, self.start = 1, False, _PENDING
            elif not inp:
                self.state, self.q = 0, False
            elif self.state == 1 and ran_out:
                self.state, self.q = 2, True
        elif self.typ == "TOF":
            if self.state == 0 and self.prev_in and not inp:
                self.state, self.start = 1, _PENDING
            elif inp:
                self.state = 0
            elif self.state == 1 and ran_out:
                self.state = 2
            self.q = inp or self.state == 1
        else:  # TP
            if up:
                self.state, self.q, self.start = 1, True, _PENDING
            elif self.state == 1 and ran_out:
                self.state, self.q = 2, False
            if self.state == 2 and not inp:
                self.state = 0
        self.prev_in = inp


def _split_args(text: str) -> list[str]:
    out, depth, cur = [], 0, ""
    for ch in text:
        depth += {"(": 1, ")": -1}.get(ch, 0)
        if ch == "," and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    return [*out, cur] if cur.strip() else out


def run_statements(text: str, env: dict[str, Any], fbs: dict[str, RefFb] | None = None,
                   cur: int = 0, flags: dict[str, bool] | None = None) -> None:
    fbs = fbs or {}

    def value(expr: str) -> Any:
        return Eval(expr, env | (flags or {}) | {f"{n}.Q": fb.q for n, fb in fbs.items()}
                    ).expr()

    for stmt in (s for s in text.split(";") if s.strip()):
        call = re.fullmatch(r"\s*(\w+)\s*\((.*)\)\s*", stmt, re.DOTALL)
        if call is not None and call[1].upper() in fbs:
            args = {}
            for arg in _split_args(call[2]):
                name, _, expr = arg.partition(":=")
                args[name.strip().upper()] = value(expr)
            fbs[call[1].upper()].call(args, cur)
            continue
        target, _, expr = stmt.partition(":=")
        env[target.strip()] = value(expr)


class RefSfc:
    """The chart's state; `scan(now_ms, inputs)` runs one cycle."""

    def __init__(self, chart: RefChart) -> None:
        self.c = chart
        self.active = set(chart.initial)
        self.since: dict[str, int | None] = dict.fromkeys(chart.initial, None)
        self.env: dict[str, Any] = {v: (False if t == "BOOL" else 0)
                                    for v, t in chart.types.items() if t not in FB_TYPES}
        self.fbs = {v.upper(): RefFb(t) for v, t in chart.types.items() if t in FB_TYPES}
        self.now, self.prev = -(10 ** 9), -(10 ** 9)  # this scan's and the previous one's
        self.pulsed: set[str] = set()
        self.latched: dict[str, int | None] = {}  # SD/SL BOOL -> when its TON started

    def scan(self, now_ms: int, inputs: dict[str, Any]) -> None:
        self.env.update(inputs)
        self.prev, self.now = self.now, now_ms
        for fb in self.fbs.values():
            if fb.start == _PENDING:
                fb.start = now_ms  # a timer started in the last scan counts from this one
        for var, start in self.latched.items():
            if start is None:
                self.latched[var] = now_ms  # the TON sees the latch from this scan on
        for s in self.active:
            if self.since[s] is None:
                self.since[s] = now_ms  # the first scan the step is active in
        env = dict(self.env)
        for s in self.c.steps:
            env[f"{s}.X"] = s in self.active
            start = self.since.get(s)
            env[f"{s}.T"] = now_ms - start if s in self.active and start is not None else 0
        env |= {f"{n}.Q": fb.q for n, fb in self.fbs.items()}
        left, entered, free = set(), set(), set(self.active)
        for t in sorted(self.c.transitions, key=lambda t: t.key):
            clears = t.condition(env, self.fbs) if callable(t.condition) else \
                Eval(t.condition, env).expr()
            if all(s in free for s in t.sources) and clears:
                free -= set(t.sources)
                left |= set(t.sources)
                entered |= set(t.targets)
        before = set(self.active)
        self.active = (self.active - left) | entered
        for s in entered:
            self.since[s] = None
        self._actions(before, left - entered, entered - (before - left), now_ms)

    def _actions(self, before: set[str], gone: set[str], new: set[str], now: int) -> None:
        for net in self.c.nets:  # the blocks first, on the variables as the last scan left them
            net.run_blocks(self.env, self.fbs, self.prev)
        for var in self.pulsed:
            self.env[var] = False
        self.pulsed = set()
        for step, qual, name in self.c.actions:
            if qual not in ("L", "D", "DS"):
                continue
            start = self.since.get(step)
            elapsed = now - start if step in self.active and start is not None else 0
            done = step in self.active and elapsed >= self.c.durations[(step, name)]
            if qual == "L":
                self.env[name] = step in self.active and not done
            elif qual == "D" or done:
                self.env[name] = done
        self._stored(now)
        for step, qual, name in self.c.actions:
            body = self.c.bodies.get(name)
            runs = (qual == "N" and (step in self.active or step in gone)) or \
                (qual == "P1" and step in new) or (qual == "P0" and step in gone)
            if body is not None and runs:
                run_statements(body, self.env, self.fbs, self.prev,
                               {f"{s}.X": s in self.active for s in self.c.steps})
        for qual, value in (("S", True), ("R", False)):
            for step, q, name in self.c.actions:
                if q == qual and step in new:
                    self.env[name] = value
        for step, qual, name in self.c.actions:
            if name not in self.c.bodies and ((qual in ("P", "P1") and step in new) or
                                              (qual == "P0" and step in gone)):
                self.env[name] = True
                self.pulsed.add(name)
        for _step, qual, name in self.c.actions:
            if qual == "N" and name not in self.c.bodies:
                self.env[name] = any(s in self.active for s, q, n in self.c.actions
                                     if q == "N" and n == name)

    def _stored(self, now: int) -> None:
        for step, qual, name in self.c.actions:
            if qual not in ("SD", "SL"):
                continue
            if any(q == "R" and n == name and s in self.active for s, q, n in self.c.actions):
                self.latched.pop(name, None)  # RS: the reset dominates
            elif step in self.active and name not in self.latched:
                self.latched[name] = None
            start = self.latched.get(name, -1)
            done = start is not None and start >= 0 and \
                now - start >= self.c.durations[(step, name)]
            self.env[name] = name in self.latched and (done if qual == "SD" else not done)
