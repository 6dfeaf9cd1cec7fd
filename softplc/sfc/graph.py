"""The SFC body's wiring -> steps and transitions with their preceding and following steps.

Owns: the backwards wiring of PLCopen (connectionPointIn/connection@refLocalId names the
predecessor), dissolving selection and simultaneous divergences and convergences (as Beremiz
does when it writes textual SFC: every transition becomes FROM (steps) TO (steps)), jumps
resolved by step name, and the left-to-right order of a selection divergence's branches.
Does not know: conditions' text, actions, YAML.
"""

from __future__ import annotations

from softplc.core.problems import Problem
from softplc.core.xmltree import Node
from softplc.sfc.model import Step

WIRING = ("selectionDivergence", "selectionConvergence", "simultaneousDivergence",
          "simultaneousConvergence")


def preds(node: Node) -> list[str]:
    """The localIds wired into this object (convergences have several connectionPointIn)."""
    return [c.attrs.get("refLocalId", "") for pin in node.all("connectionPointIn")
            for c in pin.all("connection")]


class Wiring:
    def __init__(self, sfc: Node, filename: str, problems: list[Problem]) -> None:
        self.filename, self.problems = filename, problems
        self.objs = {n.attrs["localId"]: n for n in sfc.children if "localId" in n.attrs}
        self.succ: dict[str, list[str]] = {}
        for lid, node in self.objs.items():
            for p in preds(node):
                self.succ.setdefault(p, []).append(lid)
        self.steps: dict[str, Step] = {}
        for node in sfc.children:
            if node.tag == "macroStep":
                self.problem(node, "macro steps are not supported (none of the editors' "
                             "files seen writes one): inline its body")
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
