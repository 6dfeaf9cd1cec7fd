"""The fast path of the YAML loader: parser events -> values, without PyYAML's recursive
composer, for what every program file is (plain mappings, lists, scalars, anchors).

Owns: building from libyaml's events (PyYAML's own parser when libyaml is absent) exactly
what the reference loader (yamlref.Loader) builds: values, lines, problems, alias-expanded
sizes; the nesting limit, checked as it goes; which texts libyaml reads otherwise than
PyYAML (those go to PyYAML's parser). What it does not handle it leaves to the reference
loader by raising Unsupported.
Does not know: what a program means; the size limit on aliases (yamlload.py).
"""

from __future__ import annotations

import re
from typing import Any

import yaml

from softplc.core.errors import SoftplcError
from softplc.core.problems import Problem
from softplc.program.yamlref import BOOL_TAG, Loader, YList, YMap, key_problem

# Collections inside each other: programs nest about 6 deep; PyYAML's recursive loader
# fails at about 250, libyaml's composer crashes the process at about 100,000.
MAX_NESTING = 200

STR_TAG = "tag:yaml.org,2002:str"
INT_TAG = "tag:yaml.org,2002:int"
_COLLECTION_TAGS = {
    yaml.MappingStartEvent: (None, "!", "tag:yaml.org,2002:map"),
    yaml.SequenceStartEvent: (None, "!", "tag:yaml.org,2002:seq"),
}
# Implicit resolvers by first character, the wildcard ones appended (as Resolver.resolve).
_WILDCARD: list[tuple[str, re.Pattern[str]]] = Loader.yaml_implicit_resolvers.get(None, [])
_RESOLVERS = {first: resolvers + _WILDCARD
              for first, resolvers in Loader.yaml_implicit_resolvers.items() if first is not None}
_SCALARS = {tag: Loader.yaml_constructors[tag] for tag in (
    "tag:yaml.org,2002:null", BOOL_TAG, "tag:yaml.org,2002:int", "tag:yaml.org,2002:float",
    "tag:yaml.org,2002:timestamp")}
_SCALAR_CONSTRUCTOR = yaml.constructor.SafeConstructor()
NON_PRINTABLE = yaml.reader.Reader.NON_PRINTABLE
_NO_KEY = object()


class PyEvents(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser):
    """PyYAML's own parser, for when libyaml is absent: a state machine, not recursive."""

    def __init__(self, text: str) -> None:
        yaml.reader.Reader.__init__(self, text)
        yaml.scanner.Scanner.__init__(self)
        yaml.parser.Parser.__init__(self)

    def dispose(self) -> None:
        self.states, self.state = [], None


CParser: Any = None
if yaml.__with_libyaml__:
    from yaml._yaml import CParser as CParser  # libyaml: events parsed in C

# Where libyaml and PyYAML read the same text differently (found by a differential fuzz):
# tabs, `?` in flow scalars, `|#`, other line breaks and BOMs. Text with any of them outside
# comments goes to PyYAML's parser: slower, and exactly what the reference loader reads.
_DIVERGENT = re.compile(r"[\t\r\x85\u2028\u2029\ufeff?]|[|>][-+0-9]*#")
_COMMENT = re.compile(r"(?:^|(?<=[ \t]))#[^\n\r\x85\u2028\u2029]*", re.MULTILINE)


def libyaml_agrees(text: str) -> bool:
    return _DIVERGENT.search(text) is None or _DIVERGENT.search(_COMMENT.sub("", text)) is None


class TooDeep(SoftplcError):
    """The document nests collections deeper than MAX_NESTING."""


class Unsupported(SoftplcError):
    """What `build` leaves to the reference loader: explicit tags, bad literals, undefined
    or recursive aliases, several documents, every syntax error (for its exact message)."""


class Built:
    __slots__ = ("data", "expanded", "own", "problems")

    def __init__(self, data: Any, expanded: int, own: int, problems: list[Problem]) -> None:
        self.data, self.expanded, self.own, self.problems = data, expanded, own, problems


class _Open:
    """A collection being built, its sizes (see yamlload._expanded_size) and, in a mapping, the key
    waiting for its value; `skip` marks a rejected key whose value the reference loader
    never constructs: (problems, anchors) counts when the value began."""

    __slots__ = ("anchor", "expanded", "key", "key_line", "own", "skip", "value")

    def __init__(self, value: YMap | YList, anchor: str | None) -> None:
        self.value, self.anchor = value, anchor
        self.expanded = self.own = 1
        self.key: Any = _NO_KEY
        self.key_line = 0
        self.skip: tuple[int, int] | None = None


def build(source: Any, text: str, filename: str) -> Built:
    """The reference loader's result for `text`, from a flat walk over the parser's events:
    the same values, lines, problems and sizes; no recursion, so depth is checked as it goes."""
    events = source(text)
    builder = _Builder(filename, libyaml=source is CParser)
    try:
        return builder.document(events)
    except Unsupported:
        _drain(events, len(builder.stack))  # a deep document is still refused at once
        raise
    except yaml.YAMLError:
        raise Unsupported from None
    finally:
        events.dispose()


def _drain(events: Any, depth: int) -> None:
    """Read the rest of the stream for its depth alone."""
    try:
        while (kind := type(events.get_event())) is not yaml.StreamEndEvent:
            if kind in _COLLECTION_TAGS:
                depth += 1
                if depth > MAX_NESTING:
                    raise TooDeep
            elif kind is yaml.MappingEndEvent or kind is yaml.SequenceEndEvent:
                depth -= 1
    except yaml.YAMLError:
        pass


class _Builder:
    def __init__(self, filename: str, libyaml: bool) -> None:
        self.filename, self.libyaml = filename, libyaml
        self.problems: list[Problem] = []
        self.anchors: dict[str, tuple[Any, int, int, int] | None] = {}  # None while open
        self.stack: list[_Open] = []
        self.root: Built | None = None

    def document(self, events: Any) -> Built:
        events.get_event()  # stream start
        if type(events.peek_event()) is yaml.StreamEndEvent:
            return Built(None, 1, 1, [])
        events.get_event()  # document start
        next_event, event = events.get_event, self.event  # bound once: ~10**5 events
        while self.root is None:
            event(next_event())
        events.get_event()  # document end
        if type(events.get_event()) is not yaml.StreamEndEvent:
            raise Unsupported  # several documents
        return self.root

    def event(self, ev: Any) -> None:
        kind = type(ev)
        if kind is yaml.ScalarEvent:
            if self.libyaml and (ev.tag is not None or (ev.value == "" and self.marked())):
                raise Unsupported  # libyaml resolves `!` and marks empty scalars otherwise
            value = self.scalar(ev)
            line = ev.start_mark.line + 1
            if ev.anchor is not None:
                self.anchor(ev.anchor, (value, line, 1, 1))
            self.add(value, line, 1, 1)
        elif kind is yaml.MappingEndEvent or kind is yaml.SequenceEndEvent:
            done = self.stack.pop()
            if done.anchor is not None:
                self.anchors[done.anchor] = (done.value, done.value.line, done.expanded, 0)
            self.add(done.value, done.value.line, done.expanded, done.own)
        elif kind in _COLLECTION_TAGS:
            self.start(ev, kind)
        elif kind is yaml.AliasEvent:
            target = self.anchors.get(ev.anchor)
            if target is None:
                raise Unsupported  # undefined, or recursive: the reference loader says which
            self.add(*target)
        else:
            raise Unsupported

    def marked(self) -> bool:
        """Whether the next value's line is kept: all but a mapping's values."""
        top = self.stack[-1] if self.stack else None
        return top is None or type(top.value) is YList or top.key is _NO_KEY

    def start(self, ev: Any, kind: Any) -> None:
        if ev.tag not in _COLLECTION_TAGS[kind]:
            raise Unsupported
        value: YMap | YList
        if kind is yaml.MappingStartEvent:
            value = YMap()
            value.lines = {}
        else:
            value = YList()
            value.lines = []
        value.line = ev.start_mark.line + 1
        if ev.anchor is not None:
            self.anchor(ev.anchor, None)
        self.stack.append(_Open(value, ev.anchor))
        if len(self.stack) > MAX_NESTING:
            raise TooDeep

    def anchor(self, name: str, target: tuple[Any, int, int, int] | None) -> None:
        if name in self.anchors:
            raise Unsupported  # a duplicate anchor
        self.anchors[name] = target

    def scalar(self, ev: Any) -> Any:
        tag = ev.tag
        value = ev.value
        if tag is None and value.isdigit() and value.isascii() and value[0] != "0" \
                and ev.implicit[0]:
            tag = INT_TAG  # what the resolvers say, faster: weights, tokens, priorities
        elif tag is None or tag == "!":
            tag = STR_TAG
            if ev.implicit[0]:
                for candidate, regexp in _RESOLVERS.get(value[:1], _WILDCARD):
                    if regexp.match(value):
                        tag = candidate
                        break
        if tag == STR_TAG:
            return value
        if tag == INT_TAG and value.isdigit() and value.isascii() and value[0] != "0":
            try:
                return int(value)  # as construct_yaml_int does for plain decimals
            except ValueError:  # more digits than int() takes
                raise Unsupported from None
        construct = _SCALARS.get(tag)
        if construct is None:
            raise Unsupported
        node = yaml.ScalarNode(tag, value, ev.start_mark, ev.end_mark, ev.style)
        try:
            return construct(_SCALAR_CONSTRUCTOR, node)
        except (ValueError, LookupError, AttributeError):
            raise Unsupported from None

    def add(self, value: Any, line: int, expanded: int, own: int) -> None:
        if not self.stack:
            self.root = Built(value, expanded, own, self.problems)
            return
        top = self.stack[-1]
        into = top.value
        if type(into) is YList:
            into.append(value)
            into.lines.append(line)
        elif top.key is _NO_KEY:
            self.key(top, value, line)
            return
        else:
            if self.value(top, value):
                return
            expanded += 1  # the key
            own += 1
        top.expanded += expanded
        top.own += own

    def key(self, top: _Open, key: Any, line: int) -> None:
        top.key, top.key_line = key, line
        if type(key) is str and key not in top.value:
            return  # the common case, without a call
        problem = key_problem(top.value, key, line, self.filename)  # type: ignore[arg-type]
        if problem is not None:
            self.problems.append(problem)
            top.skip = (len(self.problems), len(self.anchors))

    def value(self, top: _Open, value: Any) -> bool:
        """Store the value of the waiting key; True when it is dropped (rejected key)."""
        key, top.key = top.key, _NO_KEY
        if top.skip is None:
            top.value[key] = value
            top.value.lines[key] = top.key_line
            return False
        problems, anchors = top.skip
        top.skip = None
        if len(self.anchors) != anchors:
            raise Unsupported  # the reference loader builds those at their first alias
        del self.problems[problems:]
        return True
