"""PLCopen TC6 XML (tc6_0201, tc6_0200, tc6.xsd) -> Chart: conditions and actions.

Owns: the three (four) forms of a transition condition (inline ST, a named transition's ST,
FBD or LD body, an inVariable or an FBD/LD network wired into it, the 2008 bare connection;
sfc/fbd.py writes a network's ST, its function blocks' calls become one every-scan action
on no step), the split of a condition into step-flag arcs, a step-time delay and a guard,
and actions with their qualifiers: what maps soundly onto the net and the located refusal
of the rest (docs/sfc.md).
Does not know: YAML, the engine.
"""

from __future__ import annotations

from softplc.core.problems import Problem, ProgramError
from softplc.core.xmltree import Node as XNode
from softplc.core.xmltree import parse_xml
from softplc.sfc.fbd import EVERY_SCAN, FbdError, Network, named_output
from softplc.sfc.graph import Wiring, position
from softplc.sfc.model import Action, Chart, Transition, Variable
from softplc.sfc.pous import choose_pou, variables
from softplc.sfc.st import (
    STEP_X,
    TIME,
    Expr,
    Flag,
    Node,
    StError,
    emit,
    parse_condition,
    parse_statements,
    time_ms,
)

BOOL_QUALIFIERS = {"N", "S", "R", "P", "P1", "P0"}
CODE_QUALIFIERS = {"N", "P1", "P0"}
TIMED = {"L", "D", "DS", "SD", "SL"}  # on BOOL variables: timed.py, stored.py
REFUSED_TIMED = {"DL"}


def read_chart(data: bytes, filename: str, pou_name: str | None = None) -> Chart:
    """Raises ProgramError with every located problem; nothing partial comes out."""
    root = parse_xml(data, filename)
    pou = choose_pou(root, filename, pou_name)
    problems: list[Problem] = []
    chart = Chart(filename, pou.attrs.get("name", "chart"), pou.line)
    chart.variables = variables(root, pou, filename, problems)
    sfc = pou.child("body").child("SFC")  # type: ignore[union-attr]  # choose_pou checked
    wiring = Wiring(sfc, filename, problems)  # type: ignore[arg-type]
    chart.steps = list(wiring.steps.values())
    _Reader(chart, pou, wiring, problems).read()
    if problems:
        raise ProgramError(sorted(set(problems)))
    return chart


class _Reader:
    def __init__(self, chart: Chart, pou: XNode, wiring: Wiring,
                 problems: list[Problem]) -> None:
        self.chart, self.pou, self.wiring, self.problems = chart, pou, wiring, problems
        self.names = {k: (v.name, v.kind) for k, v in chart.variables.items()}
        self.steps = {s.upper(): s for s in wiring.steps}
        self.network = Network(wiring.objs.values(), self.names)
        self.calls: list[tuple[str, int, str]] = []  # FB calls of wired networks (every scan)

    def problem(self, line: int, message: str) -> None:
        self.problems.append(Problem(self.chart.file, line, "", message))

    def read(self) -> None:
        edges = [(n, self.wiring.sources(n)) for n in self.wiring.transitions()]
        ranks = self.wiring.ranks(edges)
        used: set[str] = set(self.wiring.steps)
        for node, sources in edges:
            targets = self.wiring.targets(node)
            if not sources or not targets:
                side = "previous" if not sources else "next"
                self.problem(node.line, f"transition not connected to a {side} step")
                continue
            text, line, negated, name = self._condition(node)
            tname = _unique(name or f"{'_'.join(sources)}_to_{'_'.join(targets)}", used)
            t = Transition(tname, node.line, tuple(sources), tuple(dict.fromkeys(targets)),
                           ("NOT (" + text + ")") if negated else text,
                           rank=ranks.get(node.attrs["localId"], 0), xy=position(node))
            if text is not None:
                self._guard(t, text, line, negated, self._steps_in(node))
            self.chart.transitions.append(t)
        for block in (n for n in self.wiring.objs.values() if n.tag == "actionBlock"):
            self._actions(block)
        self._every_scan([*self.network.calls, *self.calls])

    def _condition(self, node: XNode) -> tuple[str, int, bool, str | None]:
        cond = node.child("condition")
        if cond is None:
            self.problem(node.line, "transition without a condition (write TRUE if meant)")
            return "FALSE", node.line, False, None
        negated = cond.attrs.get("negated", "false").lower() in ("true", "1")
        if (inline := cond.child("inline")) is not None:
            return inline.all_text(), _text_line(inline), negated, None
        if (ref := cond.child("reference")) is not None:
            text, line = self._named_transition(ref)
            return text, line, negated, ref.attrs.get("name")
        pin = cond.child("connectionPointIn") or cond
        links = [c.attrs.get("refLocalId", "") for c in pin.all("connection")]
        obj = self.wiring.objs.get(links[0]) if len(links) == 1 else None
        if obj is not None and obj.tag == "inVariable" and obj.child("expression") is not None \
                and obj.attrs.get("negated", "false").lower() not in ("true", "1"):
            expr = obj.child("expression")
            return expr.all_text(), expr.line, negated, None  # type: ignore[union-attr]
        wired = self._wired(self.network, pin, cond.line)
        return wired or "FALSE", cond.line, negated, None

    def _wired(self, network: Network, pin: XNode, line: int) -> str | None:
        """The ST a network (FBD blocks, LD contacts) wired into `pin` computes."""
        try:
            return network.pin(pin, "the condition", line)
        except FbdError as exc:
            self.problem(exc.line, exc.message)
            return None

    def _named_transition(self, ref: XNode) -> tuple[str, int]:
        name = ref.attrs.get("name", "")
        bodies = [t for ts in self.pou.all("transitions") for t in ts.all("transition")
                  if t.attrs.get("name", "").upper() == name.upper()]
        body = bodies[0].child("body") if bodies else None
        st = body.child("ST") if body is not None else None
        graphic = next((body.child(k) for k in ("FBD", "LD") if body is not None and
                        body.child(k) is not None), None)
        if st is None and graphic is not None:
            return self._graphic_transition(name, graphic, ref.line)
        if st is None:
            kind = body.children[0].tag if body is not None and body.children else "no"
            self.problem(ref.line, f"named transition {name!r} has {kind} body: only ST, FBD "
                         "and LD bodies are supported")
            return "FALSE", ref.line
        return st.all_text(), _text_line(st)

    def _graphic_transition(self, name: str, body: XNode, line: int) -> tuple[str, int]:
        """An FBD/LD body: its outVariable or coil named after the transition is the value."""
        out = named_output(body, name)
        if out is None:
            self.problem(line, f"named transition {name!r}: its {body.tag} body holds no "
                         f"outVariable or coil named {name} (the transition's value)")
            return "FALSE", line
        network = Network(body.children, self.names)
        pin = out.child("connectionPointIn")
        text = self._wired(network, pin if pin is not None else out, out.line)
        self.calls.extend(network.calls)
        return text or "FALSE", out.line

    def _steps_in(self, node: XNode) -> dict[str, str]:
        """The steps ST names in this object: inside a macro step, its own steps go by their
        names in the macro's body (`Fill.X` in macro Tank is Tank.Fill), as the editor shows."""
        prefix = self.wiring.scope.get(node.attrs.get("localId", ""), "").upper()
        inner = {k[len(prefix):]: v for k, v in self.steps.items() if prefix and
                 k.startswith(prefix)}
        return {**self.steps, **inner} if inner else self.steps

    def _guard(self, t: Transition, text: str, line: int, negated: bool,
               steps: dict[str, str]) -> None:
        try:
            expr = parse_condition(text, self.names, steps)
            if negated:
                expr = Node("not", (expr,))
            terms = _conjuncts(expr)
            rest = [term for term in terms if not self._flag(t, term, len(terms))]
            guard = emit(Node("AND", tuple(rest))) if len(rest) > 1 else \
                emit(rest[0]) if rest else ("", "bool")
        except StError as exc:
            self.problem(line + text[:exc.offset].count("\n"), f"transition {t.name}: "
                         f"{exc.message}")
            return
        if guard[1] != "bool" and guard[0] not in ("0", "1"):
            self.problem(line, f"transition {t.name}: condition {text.strip()!r} is "
                         f"{guard[1].upper()}, expected BOOL")
        t.guard = {"1": "", "true": "", "0": "false"}.get(guard[0], guard[0])
        t.never = t.guard == "false"

    def _flag(self, t: Transition, term: Expr, count: int) -> bool:
        """A step flag standing as one conjunct: becomes an arc or the delay (True)."""
        if isinstance(term, Flag) and term.flag == "X":
            if term.step not in t.sources:
                t.reads += (term.step,)
            return True
        if isinstance(term, Node) and term.op == "not" and isinstance(term.args[0], Flag) \
                and term.args[0].flag == "X":
            if term.args[0].step in t.sources:
                raise StError(f"NOT {term.args[0].step}.X of the transition's own preceding "
                              "step: it can never clear", term.offset)
            t.inhibits += (term.args[0].step,)
            return True
        if isinstance(term, Node) and term.op in (">=", ">") and term.args and \
                isinstance(term.args[0], Flag) and term.args[0].flag == "T":
            flag, bound = term.args[0], term.args[1]
            if term.op == ">" or count != 1 or flag.step not in t.sources or \
                    not (isinstance(bound, Node) and bound.op == "lit" and bound.kind == TIME):
                raise StError(f"{flag.step}.T: supported only as the whole condition "
                              f"`{flag.step}.T >= T#...` of a transition leaving {flag.step} "
                              "(softplc's delay restarts when a guard goes false, a step "
                              "timer does not)", term.offset)
            t.delay_ms = int(bound.text)
            return True
        return False

    def _actions(self, block: XNode) -> None:
        refs = [r for pin in block.all("connectionPointIn") for c in pin.all("connection")
                if (r := c.attrs.get("refLocalId", ""))]
        step_node = self.wiring.objs.get(refs[0]) if refs else None
        if step_node is None or step_node.tag != "step":
            self.problem(block.line, "action block not connected to a step")
            return
        for act in block.all("action"):
            self._action(step_node.attrs.get("name", ""), act, self._steps_in(block))

    def _action(self, step: str, act: XNode, steps: dict[str, str]) -> None:
        qual = (act.attrs.get("qualifier") or "N").upper()
        duration = act.attrs.get("duration", "")
        ref = act.child("reference")
        name = ref.attrs.get("name", "") if ref is not None else f"{step}_inline{act.line}"
        if qual in REFUSED_TIMED:
            self.problem(act.line, f"action {name} of step {step}: qualifier {qual} "
                         f"{duration} is in the PLCopen schema only: IEC 61131-3 defines no "
                         "ACTION_CONTROL rule for it, so there is nothing to map (supported: N, "
                         "S, R, P, P1, P0, and L, D, DS, SD, SL with a duration, on BOOL "
                         "variables; N, P1, P0 on ST bodies)")
            return
        var = self.chart.variables.get(name.upper()) if ref is not None else None
        if qual in TIMED:
            self._timed(step, qual, name, duration, var, act.line)
            return
        var = self.chart.variables.get(name.upper()) if ref is not None else None
        if var is not None:
            if var.kind != "bool" or qual not in BOOL_QUALIFIERS:
                self.problem(act.line, f"action {name} of step {step}: a variable as an "
                             f"action must be BOOL (it is {var.iec}), qualifier N S R P P1 P0")
                return
            self.chart.actions.append(Action(step, qual, var.name, act.line, var.name))
            return
        text, line = self._action_body(act, name)
        if text is None:
            return
        if qual not in CODE_QUALIFIERS:
            why = "runs twice (the pulse and the final execution, IEC 2.6.4.5)" if qual == \
                "P" else "is stored: it would run every scan until reset"
            self.problem(act.line, f"action {name} of step {step}: {qual} with an ST body "
                         f"{why}; supported: N, P1, P0 bodies, or a BOOL variable as the action")
            return
        try:
            stmts = [(v, self._assign(v, k, e)) for v, k, e, _ in
                     parse_statements(text, self.names, steps)]
        except StError as exc:
            self.problem(line + text[:exc.offset].count("\n"), f"action {name}: {exc.message}")
            return
        self.chart.actions.append(Action(step, qual, name, act.line, None, tuple(stmts)))

    def _timed(self, step: str, qual: str, name: str, duration: str,
                var: Variable | None, line: int) -> None:
        if var is None or var.kind != "bool":
            self.problem(line, f"action {name} of step {step}: {qual} {duration} is supported "
                         "on a BOOL variable only (an ST body would need a per-scan timer)")
            return
        try:
            ms = time_ms(duration.strip(), 0) if duration.strip() else 0
        except StError as exc:
            self.problem(line, f"action {name} of step {step}: duration: {exc.message}")
            return
        if ms <= 0:
            self.problem(line, f"action {name} of step {step}: qualifier {qual} needs a "
                         f"positive duration (duration=\"T#2s\"), got {duration!r}")
            return
        self.chart.actions.append(Action(step, qual, var.name, line, var.name,
                                         duration=duration.strip(), duration_ms=ms))

    def _assign(self, var: str, kind: str, expr: Expr) -> str:
        text, got = emit(expr)
        fits = got == kind or (kind == "real" and got == "int") or \
            (kind == "bool" and text in ("0", "1"))
        if not fits:
            raise StError(f"{var} := {text}: {got.upper()} written to {kind.upper()}", 0)
        return text

    def _action_body(self, act: XNode, name: str) -> tuple[str | None, int]:
        if (inline := act.child("inline")) is not None:
            body: XNode | None = inline
        else:
            found = [a for acts in self.pou.all("actions") for a in acts.all("action")
                     if a.attrs.get("name", "").upper() == name.upper()]
            if not found:
                self.problem(act.line, f"action {name!r}: neither a POU action nor a variable")
                return None, act.line
            body = found[0].child("body")
        st = body.child("ST") if body is not None else None
        if st is None:
            kind = body.children[0].tag if body is not None and body.children else "an empty"
            self.problem(act.line, f"action {name!r} has a {kind} body: only ST is supported")
            return None, act.line
        return st.all_text(), _text_line(st)


    def _every_scan(self, calls: list[tuple[str, int, str]]) -> None:
        """The FB instances of wired networks run every scan, in one action on no step
        (emit.py: a self-loop on an always-marked place), as Beremiz's hidden
        COMPUTE_FUNCTION_BLOCKS does."""
        stmts: list[tuple[str, str]] = []
        for call, line, block in calls:
            try:
                parsed = parse_statements(call, self.names, self.steps)
                if any(STEP_X in emit(e)[0] for _, _, e, _ in parsed):
                    raise StError(f"{call.strip()} reads a step's X: a block in the SFC body "
                                  "runs every scan, where softplc's statements do not read a "
                                  "step's activity; drive a BOOL with an N action on the step "
                                  "and wire that (as the OpenPLC Editor's charts do)", 0)
                stmts += [(v, self._assign(v, k, e)) for v, k, e, _ in parsed]
            except StError as exc:
                self.problem(line, f"{block} in the SFC body: {exc.message}")
        if stmts and not self.problems:
            name = _unique(EVERY_SCAN, {s.upper() for s in self.wiring.steps})
            self.chart.actions.append(Action("", "N", name, calls[0][1], None, tuple(stmts)))


def _conjuncts(expr: Expr) -> list[Expr]:
    if isinstance(expr, Node) and expr.op == "AND":
        return [t for a in expr.args for t in _conjuncts(a)]
    return [expr]


def _text_line(node: XNode) -> int:
    """The line where the body's text starts (the first descendant holding text)."""
    for n in node.walk():
        if n.text.strip():
            return n.line + n.text[:len(n.text) - len(n.text.lstrip())].count("\n")
    return node.line


def _unique(name: str, used: set[str]) -> str:
    out, n = name, 2
    while out in used:
        out, n = f"{name}_{n}", n + 1
    used.add(out)
    return out
