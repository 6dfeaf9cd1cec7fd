"""How other tools write P/T nets in PNML: their net types and label styles.

Owns: the net types read as P/T nets (the ISO `ptnet`, the `pnmlcoremodel` of ProM and pm4py,
the pre-ISO `ptNetb` of WoPeD/PNK, PIPE's "P/T net") and why any other type is refused; a
label's text (`<text>`, or PIPE's `<value>`), PIPE's "Default,1" counts, an arc's kind
(pm4py's `<arctype>`, PIPE's `<type value>`); where a net's nodes sit (under <net>, in
pages, in nested pages).
Does not know: the net's structure, softplc's own data, files.
"""

from __future__ import annotations

from collections.abc import Iterator

from softplc.core.xmltree import Node

# Normalised (lower case, no trailing "#" or "/") type -> the tool family, for notes.
PT_TYPES = {
    "http://www.pnml.org/version-2009/grammar/ptnet": "ISO ptnet",
    "http://www.pnml.org/version-2009/grammar/ptnet.pntd": "ISO ptnet",
    "http://www.pnml.org/version-2011/grammar/ptnet": "ISO ptnet",
    # The core model gives arcs no weights and places no markings; ProM and pm4py write
    # both anyway, as P/T nets.
    "http://www.pnml.org/version-2009/grammar/pnmlcoremodel": "pnmlcoremodel",
    "http://www.informatik.hu-berlin.de/top/pntd/ptnetb": "ptNetb (WoPeD, PNK)",
    "http://www.informatik.hu-berlin.de/top/pnml/ptnetb": "ptNetb (WoPeD, PNK)",
    "http://www.informatik.hu-berlin.de/top/pntd/ptnet": "ptNet (PNK)",
    "p/t net": "PIPE",
}
_NOT_PT = ("symmetricnet", "hlpn", "pt-hlpng", "coloured", "colored", "stochastic", "gspn")


def normal_type(net_type: str) -> str:
    return net_type.strip().rstrip("#/").lower()


def type_problem(net_type: str | None) -> str | None:
    """Why a net of this type is not read, or None when it is read as a P/T net."""
    if net_type is not None and normal_type(net_type) in PT_TYPES:
        return None
    why = ("high-level and coloured nets are not read"
           if net_type and any(k in net_type.lower() for k in _NOT_PT)
           else "not a P/T net type softplc reads")
    return (f"net type {net_type!r}: {why}; only P/T nets are read: the ISO ptnet, "
            "pnmlcoremodel as ProM and pm4py write it, WoPeD's ptNetb, PIPE's \"P/T net\"")


def label(node: Node, tag: str) -> str | None:
    """The text of `node`'s `tag` label: `<tag><text>` (ISO, WoPeD, ProM) or `<tag><value>`
    (PIPE)."""
    text = node.text_of(tag, "text")
    return node.text_of(tag, "value") if text is None else text


def pipe_count(text: str) -> tuple[str, str | None]:
    """PIPE writes counts as "Default,1" (token class, count; several classes for coloured
    nets): the count's text, and why it cannot be read (more than one class with tokens)."""
    if "," not in text:
        return text, None
    parts = [s.strip() for s in text.split(",")]
    if len(parts) % 2:
        return text, None  # not pairs: the caller's number check reports it
    counts = [c for c in parts[1::2] if c not in ("0", "")]
    if len(counts) > 1:
        return text, f"{text!r}: tokens of several PIPE token classes (coloured) are not read"
    return (counts[0] if counts else "0"), None


def arc_kind(arc: Node) -> str:
    """"normal", "inhibitor", or another kind (reset, read, ...) as the file names it."""
    kind = arc.text_of("arctype", "text")  # pm4py
    if kind is None:
        typed = arc.child("type")  # PIPE: <type value="inhibitor"/>
        kind = typed.attrs.get("value") if typed is not None else None
    return (kind or "normal").strip().lower()


def elements(page: Node) -> Iterator[Node]:
    """The elements of a net or page in document order, nested pages flattened (iteratively:
    pages may nest as deep as xmltree.MAX_DEPTH allows). WoPeD and PIPE put places and
    transitions directly under <net>, ISO files in pages, so both are read."""
    stack = [iter(page.children)]
    while stack:
        child = next(stack[-1], None)
        if child is None:
            stack.pop()
        elif child.tag == "page":
            stack.append(iter(child.children))
        else:
            yield child
