"""The SFC body's wiring -> steps and transitions with their preceding and following steps.

Owns: the backwards wiring of PLCopen (connectionPointIn/connection@refLocalId names the
predecessor), dissolving selection and simultaneous divergences and convergences (as Beremiz
does when it writes textual SFC: every transition becomes FROM (steps) TO (steps)), jumps
resolved by step name, the left-to-right order of a selection divergence's branches, and
macro steps expanded inline (their body's chart between its entry and exit steps, the inner
names prefixed `MACRO.`, every node keeping its XML line: docs/sfc.md).
Does not know: conditions' text, actions, YAML.
"""

from __future__ import annotations

from softplc.core.problems import Problem
from softplc.core.xmltree import Node
from softplc.sfc.model import Step

MAX_MACRO_DEPTH = 16
WIRING = ("selectionDivergence", "selectionConvergence", "simultaneousDivergence",
          "simultaneousConvergence")


def preds(node: Node) -> list[str]:
    """The localIds wired into this object (convergences have several connectionPointIn)."""
    return [c.attrs.get("refLocalId", "") for pin in node.all("connectionPointIn")
            for c in pin.all("connection")]


class Wiring:
    def __init__(self, sfc: Node, filename: str, problems: list[Problem]) -> None:
        self.filename, self.problems = filename, problems
        flat = _Macros(filename, problems)
        children = flat.level(sfc.children, "", "")
        self.scope = flat.scope  # localId -> the prefix of the macro it is in ("M1.", "")
        self.objs = {n.attrs["localId"]: n for n in children if "localId" in n.attrs}
        self.succ: dict[str, list[str]] = {}
        for lid, node in self.objs.items():
            for p in preds(node):
                self.succ.setdefault(p, []).append(lid)
        self.steps: dict[str, Step] = {}
        for node in children:
            if node.tag == "step":
                self._step(node)

    def problem(self, node: Node, message: str) -> None:
        self.problems.append(Problem(self.filename, node.line, "", message))

    def _step(self, node: Node) -> None:
        name = node.attrs.get("name", "")
        if not name or name in self.steps:
            self.problem(node, f"step {name!r}: a step needs a name unique in the chart")
            return
        x, y = position(node) or (0.0, 0.0)
        initial = node.attrs.get("initialStep", "false").lower() in ("true", "1")
        self.steps[name] = Step(name, node.line, initial, x, y)

    def step_of(self, name: str) -> str | None:
        """A step by name as ST and jumps write it: case does not matter."""
        if name in self.steps:
            return name
        return next((s for s in self.steps if s.upper() == name.upper()), None)

    def sources(self, node: Node) -> list[str]:
        out: list[str] = []
        for ref in preds(node):
            self._back(ref, out, node, 0)
        return out

    def _back(self, ref: str, out: list[str], origin: Node, depth: int) -> None:
        obj = self.objs.get(ref)
        if obj is None or depth > len(self.objs):
            self.problem(origin, f"connection to localId {ref!r}: no such object")
        elif obj.tag == "step":
            out.append(obj.attrs.get("name", ""))
        elif obj.tag in WIRING:
            for p in preds(obj):
                self._back(p, out, obj, depth + 1)
        else:
            self.problem(origin, f"a transition is preceded by a {obj.tag} (line {obj.line}); "
                         "expected a step or a divergence/convergence")

    def targets(self, node: Node) -> list[str]:
        out: list[str] = []
        self._forward(node.attrs.get("localId", ""), out, node, 0)
        return out

    def _forward(self, lid: str, out: list[str], origin: Node, depth: int) -> None:
        for nxt in self.succ.get(lid, []):
            obj = self.objs[nxt]
            if obj.tag == "step":
                out.append(obj.attrs.get("name", ""))
            elif obj.tag == "jumpStep":
                target = self.step_of(obj.attrs.get("targetName", ""))
                if target is None:
                    self.problem(obj, f"jump to {obj.attrs.get('targetName', '')!r}: no step "
                                 f"of that name (steps: {', '.join(self.steps)})")
                else:
                    out.append(target)
            elif obj.tag in WIRING and depth <= len(self.objs):
                self._forward(nxt, out, origin, depth + 1)

    def transitions(self) -> list[Node]:
        return [n for n in self.objs.values() if n.tag == "transition"]

    def ranks(self, edges: list[tuple[Node, list[str]]]) -> dict[str, int]:
        """localId -> rank among the transitions leaving the same step: the XML priority
        (lower first) where given, then left to right (position x), then document order
        (CODESYS writes every position as 0,0 and the elements in chart order)."""
        order = {id(n): i for i, n in enumerate(self.objs.values())}
        out: dict[str, int] = {}
        by_step: dict[str, list[Node]] = {}
        for node, sources in edges:
            for s in sources:
                by_step.setdefault(s, []).append(node)
        for group in by_step.values():
            group.sort(key=lambda n: (int(n.attrs.get("priority", 0) or 0), _x(n),
                                      order[id(n)]))
            for rank, n in enumerate(group):
                lid = n.attrs["localId"]
                out[lid] = max(out.get(lid, 0), rank)
        return out


def _x(node: Node) -> float:
    return (position(node) or (0.0, 0.0))[0]


def position(node: Node) -> tuple[float, float] | None:
    """The object's `<position x= y=>` as drawn; None when absent or not numbers."""
    pos = node.child("position")
    try:
        return (float(pos.attrs.get("x", 0)), float(pos.attrs.get("y", 0))) \
            if pos is not None else None
    except ValueError:
        return None


class _Macros:
    """Macro steps (PLCopen `<macroStep name><body><SFC>`; IEC 61131-3 has none) replaced by
    their body's chart: its one initial step is the entry (the macro's preceding transitions
    enter it), its one step no transition leaves is the exit (the macro's following
    transitions leave it). Inner steps are named `MACRO.Inner` and inner localIds `MID/ID`;
    a jump inside a macro names a step of the macro (unprefixed); outside, a jump to the
    macro enters its entry step. Nodes are copied, with their XML lines."""

    def __init__(self, filename: str, problems: list[Problem]) -> None:
        self.filename, self.problems = filename, problems
        self.scope: dict[str, str] = {}

    def problem(self, node: Node, message: str) -> None:
        self.problems.append(Problem(self.filename, node.line, "", message))

    def level(self, children: list[Node], prefix: str, ids: str, depth: int = 0) -> list[Node]:
        out: list[Node] = []
        ends: dict[str, tuple[str, str, str]] = {}  # macro id -> entry id, its name, exit id
        for node in children:
            if node.tag != "macroStep":
                out.append(_copy(node, ids, prefix))
                self.scope[out[-1].attrs.get("localId", "")] = prefix
            elif (done := self._macro(node, prefix, ids, depth)) is not None:
                inner, entry, exit_ = done
                out += inner
                ends[ids + node.attrs.get("localId", "")] = (
                    entry.attrs["localId"], entry.attrs["name"], exit_.attrs["localId"])
                self._enter(entry, node, ids)
            else:  # refused: a plain step in its place, so that its wires raise nothing more
                stand_in = Node("step", {**node.attrs, "name": _macro_name(node)}, node.line,
                                [c for c in node.children if c.tag != "body"])
                out.append(_copy(stand_in, ids, prefix))
                self.scope[out[-1].attrs.get("localId", "")] = prefix
        names = {n.attrs.get("name", "").upper(): prefix + n.attrs.get("name", "")
                 for n in children if n.tag == "step"}
        names.update({_macro_name(n).upper(): e[1] for n in children if n.tag == "macroStep"
                      and (e := ends.get(ids + n.attrs.get("localId", ""))) is not None})
        for node in out:
            self._rewire(node, ends)
            if node.tag == "jumpStep" and self.scope.get(node.attrs.get("localId", "")) == prefix:
                self._jump(node, names, prefix)
        return [n for n in out if not (n.tag == "actionBlock" and set(preds(n)) & set(ends))]

    def _macro(self, node: Node, prefix: str, ids: str,
               depth: int) -> tuple[list[Node], Node, Node] | None:
        name = _macro_name(node)
        body = node.child("body")
        sfc = body.child("SFC") if body is not None else None
        if sfc is None:
            kind = f"an {body.children[0].tag}" if body is not None and body.children else "no"
            self.problem(node, f"macro step {name} has {kind} body: a macro step's body must "
                         "be an SFC (<body><SFC>: its entry step, ..., its exit step)")
            return None
        if depth >= MAX_MACRO_DEPTH:
            self.problem(node, f"macro step {name}: macro steps nested more than "
                         f"{MAX_MACRO_DEPTH} deep")
            return None
        inner = self.level(sfc.children, f"{prefix}{name}.", f"{ids}{node.attrs.get('localId')}/",
                           depth + 1)
        steps = [n for n in inner if n.tag == "step"]
        entries = [n for n in steps if n.attrs.pop("initialStep", "").lower() in ("true", "1")]
        wired = {ref for n in inner if n.tag != "actionBlock" for ref in preds(n)}
        exits = [n for n in steps if n.attrs.get("localId") not in wired]
        found = [", ".join(n.attrs["name"] for n in ns) or "none" for ns in (entries, exits)]
        if len(entries) != 1:
            self.problem(node, f"macro step {name}: its body needs exactly one initial step, "
                         "the entry step the macro's preceding transitions enter; found "
                         f"{found[0]}")
        if len(exits) != 1:
            self.problem(node, f"macro step {name}: its body needs exactly one exit step (a "
                         "step no transition of the body leaves), which the macro's following "
                         f"transitions leave; found {found[1]}")
        return (inner, entries[0], exits[0]) if len(entries) == len(exits) == 1 else None

    def _enter(self, entry: Node, macro: Node, ids: str) -> None:
        """The macro's incoming wires become the entry step's (beside the body's own)."""
        pin = entry.child("connectionPointIn")
        if pin is None:
            pin = Node("connectionPointIn", {}, entry.line)
            entry.children.append(pin)
        for src in macro.all("connectionPointIn"):
            pin.children += [_copy(c, ids, "") for c in src.all("connection")]

    def _rewire(self, node: Node, ends: dict[str, tuple[str, str, str]]) -> None:
        """A wire from a macro step comes from its exit step (ids are unique per level: an
        inner id holds one more `/` than the level's)."""
        for conn in (c for c in node.walk() if c.tag == "connection"):
            ref = conn.attrs.get("refLocalId", "")
            if ref in ends and node.tag == "actionBlock":  # then left out (level())
                self.problem(node, "an action block on a macro step: attach the actions to "
                             "the steps in its body")
            elif ref in ends:
                conn.attrs["refLocalId"] = ends[ref][2]

    def _jump(self, node: Node, names: dict[str, str], prefix: str) -> None:
        target = node.attrs.get("targetName", "")
        if target.upper() in names:
            node.attrs["targetName"] = names[target.upper()]
        elif prefix:
            self.problem(node, f"jump to {target!r} in macro step {prefix[:-1]}: no step of "
                         "that name in the macro (a jump does not leave a macro: its exit "
                         "step does)")


def _macro_name(node: Node) -> str:
    return node.attrs.get("name") or f"Macro{node.attrs.get('localId', '')}"


def _copy(node: Node, ids: str, prefix: str) -> Node:
    """A copy with the localId and every refLocalId under `ids`, a step's name under
    `prefix`; jump targets are rewired by the caller."""
    attrs = dict(node.attrs)
    for key in ("localId", "refLocalId"):
        if key in attrs and ids:
            attrs[key] = ids + attrs[key]
    if node.tag == "step" and prefix:
        attrs["name"] = prefix + attrs.get("name", "")
    return Node(node.tag, attrs, node.line,
                [_copy(c, ids, "") for c in node.children], node.text)
