"""A small XML tree with line numbers, read through defusedxml's hardened SAX parser: the one
reader of the XML files programs arrive in (PNML: analysis/pnml.py; PLCopen XML: sfc/).

Owns: Node (tag without namespace, attributes, own text, line, children) and `parse_xml`, which
refuses DTDs' entity declarations and external entities (defusedxml raises on them) and
elements nested deeper than MAX_DEPTH, and turns every XML error into a located Problem.
Does not know: PNML or PLCopen.
"""

from __future__ import annotations

import xml.sax
from collections.abc import Iterator
from dataclasses import dataclass, field
from xml.sax.handler import ContentHandler
from xml.sax.xmlreader import AttributesImpl, Locator

import defusedxml.sax  # type: ignore[import-untyped]
from defusedxml import DefusedXmlException

from softplc.core.errors import SoftplcError
from softplc.core.problems import Problem, ProgramError

# PNML nests pnml/net/page/place/name/text and pages in pages (100,000 nested <page>s once
# ended `softplc analyze` in a RecursionError); PLCopen project/types/pous/pou/body/SFC/step
# about 15 deep. The tree is built and walked iteratively; this bound keeps every walk of it
# (and its repr) shallow.
MAX_DEPTH = 100


class _TooDeep(SoftplcError):
    def __init__(self, line: int) -> None:
        super().__init__(line)
        self.line = line


@dataclass(slots=True)
class Node:
    tag: str
    attrs: dict[str, str]
    line: int
    children: list[Node] = field(default_factory=list)
    text: str = ""

    def child(self, tag: str) -> Node | None:
        return next((c for c in self.children if c.tag == tag), None)

    def all(self, tag: str) -> list[Node]:
        return [c for c in self.children if c.tag == tag]

    def text_of(self, *path: str) -> str | None:
        node: Node | None = self
        for tag in path:
            node = node.child(tag) if node is not None else None
        return None if node is None else node.text.strip()

    def walk(self) -> Iterator[Node]:
        """This node and every descendant, in document order."""
        stack = [self]
        while stack:
            node = stack.pop()
            yield node
            stack.extend(reversed(node.children))

    def all_text(self) -> str:
        """Every descendant's text: PLCopen writes ST bodies as xhtml:p CDATA (Beremiz), an
        xhtml element (CODESYS) or bare text (2006-2008 files); all three read the same."""
        return "".join(n.text for n in self.walk())


class _Builder(ContentHandler):
    def __init__(self) -> None:
        super().__init__()
        self.stack: list[Node] = []
        self.root: Node | None = None
        self.locator: Locator | None = None

    def setDocumentLocator(self, locator: Locator) -> None:
        self.locator = locator

    def startElement(self, name: str, attrs: AttributesImpl) -> None:
        line = self.locator.getLineNumber() if self.locator else 0
        if len(self.stack) >= MAX_DEPTH:
            raise _TooDeep(line or 1)
        node = Node(name.rpartition(":")[2], dict(attrs.items()), line or 0)
        if self.stack:
            self.stack[-1].children.append(node)
        else:
            self.root = node
        self.stack.append(node)

    def endElement(self, name: str) -> None:
        self.stack.pop()

    def characters(self, content: str) -> None:
        if self.stack:
            self.stack[-1].text += content


def parse_xml(data: bytes, filename: str) -> Node:
    builder = _Builder()
    try:
        defusedxml.sax.parseString(data, builder, forbid_dtd=False, forbid_entities=True,
                                   forbid_external=True)
    except DefusedXmlException as exc:
        line = builder.locator.getLineNumber() if builder.locator else 0
        raise ProgramError([Problem(filename, line or 1, "", f"refused XML: {exc} (entity "
                                    "declarations and external entities are not accepted)")]
                           ) from None
    except _TooDeep as exc:
        raise ProgramError([Problem(filename, exc.line, "", f"XML nested deeper than "
                                    f"{MAX_DEPTH} elements")]) from None
    except xml.sax.SAXParseException as exc:
        raise ProgramError([Problem(filename, exc.getLineNumber() or 1, "",
                                    f"not well-formed XML: {exc.getMessage()}")]) from None
    if builder.root is None:
        raise ProgramError([Problem(filename, 1, "", "empty XML document")])
    return builder.root
