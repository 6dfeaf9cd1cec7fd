"""Which POU of a PLCopen project is the chart, and its variables.

Owns: finding SFC POUs (under types/pous, and where CODESYS puts them: resource addData),
choosing one by name, and reading the POU interface and the configuration's globals into
Variables with their IEC types, addresses and lines.
Does not know: the chart's graph, YAML.
"""

from __future__ import annotations

from softplc.core.problems import Problem, ProgramError
from softplc.core.xmltree import Node
from softplc.sfc.model import Variable

VAR_SECTIONS = ("inputVars", "outputVars", "inOutVars", "localVars", "tempVars",
                "externalVars", "globalVars")


def sfc_pous(root: Node) -> list[Node]:
    """Every POU whose body is an SFC, in document order, wherever the writer put it."""
    return [n for n in root.walk() if n.tag == "pou"
            and (body := n.child("body")) is not None and body.child("SFC") is not None]


def choose_pou(root: Node, filename: str, name: str | None) -> Node:
    pous = sfc_pous(root)
    names = ", ".join(p.attrs.get("name", "?") for p in pous) or "none"
    if root.tag != "project":
        raise ProgramError([Problem(filename, root.line, "", f"not a PLCopen TC6 project "
                                    f"(root element <{root.tag}>, expected <project>)")])
    if name is not None:
        found = [p for p in pous if p.attrs.get("name", "").upper() == name.upper()]
        if not found:
            raise ProgramError([Problem(filename, root.line, "", f"no SFC POU named {name!r}; "
                                        f"SFC POUs in the file: {names}")])
        return found[0]
    if len(pous) == 1:
        return pous[0]
    why = "no POU with an SFC body" if not pous else f"several SFC POUs ({names}): name one " \
        "with --pou POU or FILE.xml#POU"
    raise ProgramError([Problem(filename, root.line, "", why)])


def variables(root: Node, pou: Node, filename: str,
              problems: list[Problem]) -> dict[str, Variable]:
    """The POU's interface, then the globals of configurations and resources (a POU's own
    declaration wins, as in ST scoping). Keys are upper case: ST names ignore case."""
    out: dict[str, Variable] = {}
    lists = [n for n in (pou.child("interface") or Node("", {}, 0)).children
             if n.tag in VAR_SECTIONS]
    lists += [n for n in root.walk() if n.tag == "globalVars" and n not in lists]
    for section in lists:
        for var in section.all("variable"):
            v = _variable(var, section.tag, filename, problems)
            if v is not None and v.name.upper() not in out:
                out[v.name.upper()] = v
    return out


def _variable(var: Node, section: str, filename: str, problems: list[Problem]) -> Variable | None:
    name = var.attrs.get("name", "")
    typ = var.child("type")
    if not name or typ is None or not typ.children:
        problems.append(Problem(filename, var.line, "", "variable without a name or a type"))
        return None
    first = typ.children[0]
    iec = first.attrs.get("name", "?") if first.tag == "derived" else first.tag.upper()
    init = None
    if (iv := var.child("initialValue")) is not None and (sv := iv.child("simpleValue")):
        init = sv.attrs.get("value")
    return Variable(name, iec, var.attrs.get("address") or None, section, init, var.line)
