"""YAML with line numbers and without YAML 1.1 traps.

Owns: loading YAML text into plain dicts/lists/scalars that remember their line numbers;
`on`/`off`/`yes`/`no` stay text (YAML 1.2 booleans only), duplicate keys are problems; the
limits (nesting depth, alias expansion). Fast path: libyaml's parser events, built without
recursion; PyYAML's own loader is the reference and decides every odd or faulty document.
Does not know: what a program means.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

from softplc.core.problems import Problem

BOOL_TAG = "tag:yaml.org,2002:bool"
YAML11_BOOLS = frozenset({"on", "off", "yes", "no", "y", "n"})


class YMap(dict[Any, Any]):
    """A mapping that knows its own line and the line of each key."""

    line: int = 0
    lines: dict[Any, int]


class YList(list[Any]):
    line: int = 0
    lines: list[int]


class _Loader(yaml.SafeLoader):
    problems: list[Problem]
    filename: str

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, LookupError, AttributeError) as exc:
            if not isinstance(node, yaml.ScalarNode):
                raise
            # `0x_`, `2024-13-45` resolve as a number or date there is no such; `!!int ''`
            raise yaml.constructor.ConstructorError(
                None, None, _bad_literal(node, exc), node.start_mark) from None


def _bad_literal(node: yaml.Node, exc: Exception) -> str:
    kind = str(node.tag).rsplit(":", 1)[-1]
    return f"{repr(node.value)[:40]} is not a valid {kind} ({exc})"


_Loader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != BOOL_TAG]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Loader.add_implicit_resolver(
    BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


def _mapping(loader: _Loader, node: yaml.MappingNode) -> YMap:
    out = YMap()
    out.line = node.start_mark.line + 1
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        problem = _key_problem(out, key, line, loader.filename)
        if problem is not None:
            loader.problems.append(problem)
            continue
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = line
    return out


def _key_problem(out: YMap, key: Any, line: int, filename: str) -> Problem | None:
    """Why `key` cannot go into `out`, or None (its value is then never constructed)."""
    if not isinstance(key, str | int | bool):
        return Problem(filename, line, "", "keys must be plain names")
    if key in out:
        return Problem(filename, line, str(key),
                       f"duplicate key {key!r} (first at line {out.lines[key]})")
    return None


def _sequence(loader: _Loader, node: yaml.SequenceNode) -> YList:
    out = YList(loader.construct_object(child, deep=True) for child in node.value)
    out.line = node.start_mark.line + 1
    out.lines = [child.start_mark.line + 1 for child in node.value]
    return out


_Loader.add_constructor("tag:yaml.org,2002:map", _mapping)
_Loader.add_constructor("tag:yaml.org,2002:seq", _sequence)


MAX_EXPANDED_VALUES = 100_000  # the example programs have a few hundred
# Collections inside each other: programs nest about 6 deep; PyYAML's recursive loader
# fails at about 250, libyaml's composer crashes the process at about 100,000.
MAX_NESTING = 200


def load_yaml(text: str, filename: str) -> tuple[Any, list[Problem]]:
    """Parse `text`. Returns (data, problems); data is None when the text does not parse."""
    if not _found(NON_PRINTABLE, text):  # else the reader's exact message below
        source = _CParser if _CParser is not None and _libyaml_agrees(text) else _PyEvents
        try:
            built = _build(source, text, filename)
        except _TooDeep:
            return None, [Problem(filename, 1, "", "YAML error: nesting too deep")]
        except _Unsupported:
            built = None  # the reference loader decides, with its own messages
        if built is not None:
            return _checked(built.data, built.expanded, built.own, built.problems, filename)
    return _reference(text, filename)


def _reference(text: str, filename: str) -> tuple[Any, list[Problem]]:
    """PyYAML's own composer and constructor: the behaviour `_build` reproduces, used for
    what it does not handle (explicit tags, errors, several documents)."""
    try:
        loader = _Loader(text)  # the reader rejects control characters at once
    except yaml.YAMLError as exc:
        return None, [_unreadable(exc, text, filename)]
    loader.problems = []
    loader.filename = filename
    try:
        data = loader.get_single_data()
    except RecursionError:  # PyYAML composes recursively: `[[[[...` a thousand deep
        return None, [Problem(filename, 1, "", "YAML error: nesting too deep")]
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else 1
        reason = exc.problem or str(exc)
        return None, [Problem(filename, line, "", f"YAML syntax error: {reason}")]
    except yaml.YAMLError as exc:
        return None, [_unreadable(exc, text, filename)]
    finally:
        loader.dispose()
    expanded, own = _expanded_size(data)
    return _checked(data, expanded, own, loader.problems, filename)


def _checked(data: Any, expanded: int, own: int, problems: list[Problem],
             filename: str) -> tuple[Any, list[Problem]]:
    if expanded - own > MAX_EXPANDED_VALUES:
        # Aliases share one object: `&a [x, x]`, `&b [*a, *a]`, ... is small text and tiny
        # memory, but anything that walks it walks 10**9 values (a "billion laughs"). Only
        # what aliases add counts: a big net written out in full is not a bomb.
        return None, [Problem(filename, 1, "", f"YAML error: more than {MAX_EXPANDED_VALUES} "
                              "values once aliases are expanded")]
    return data, problems


def _expanded_size(data: Any) -> tuple[int, int]:
    """(values a walk of `data` visits with every alias expanded, values as written: each
    shared object once). Computed once per shared object, so it costs the real size."""
    sizes: dict[int, int] = {}
    own = 0
    stack: list[tuple[Any, bool]] = [(data, False)]
    while stack:
        value, children_done = stack.pop()
        if not isinstance(value, dict | list) or id(value) in sizes:
            continue
        children = [*value.keys(), *value.values()] if isinstance(value, dict) else value
        if children_done:
            sizes[id(value)] = 1 + sum(sizes.get(id(c), 1) for c in children)
            own += 1 + sum(1 for c in children if not isinstance(c, dict | list))
            continue
        stack.append((value, True))
        stack.extend((c, False) for c in children)
    return sizes.get(id(data), 1), own if sizes else 1


# -- the fast path: parser events -> values, without PyYAML's recursive composer -------------

STR_TAG = "tag:yaml.org,2002:str"
INT_TAG = "tag:yaml.org,2002:int"
_COLLECTION_TAGS = {
    yaml.MappingStartEvent: (None, "!", "tag:yaml.org,2002:map"),
    yaml.SequenceStartEvent: (None, "!", "tag:yaml.org,2002:seq"),
}
# Implicit resolvers by first character, the wildcard ones appended (as Resolver.resolve).
_WILDCARD: list[tuple[str, re.Pattern[str]]] = _Loader.yaml_implicit_resolvers.get(None, [])
_RESOLVERS = {first: resolvers + _WILDCARD
              for first, resolvers in _Loader.yaml_implicit_resolvers.items() if first is not None}
_SCALARS = {tag: _Loader.yaml_constructors[tag] for tag in (
    "tag:yaml.org,2002:null", BOOL_TAG, "tag:yaml.org,2002:int", "tag:yaml.org,2002:float",
    "tag:yaml.org,2002:timestamp")}
_SCALAR_CONSTRUCTOR = yaml.constructor.SafeConstructor()
NON_PRINTABLE = yaml.reader.Reader.NON_PRINTABLE
_NO_KEY = object()


class _PyEvents(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser):
    """PyYAML's own parser, for when libyaml is absent: a state machine, not recursive."""

    def __init__(self, text: str) -> None:
        yaml.reader.Reader.__init__(self, text)
        yaml.scanner.Scanner.__init__(self)
        yaml.parser.Parser.__init__(self)

    def dispose(self) -> None:
        self.states, self.state = [], None


_CParser: Any = None
if yaml.__with_libyaml__:
    from yaml._yaml import CParser as _CParser  # libyaml: events parsed in C

# Where libyaml and PyYAML read the same text differently (found by a differential fuzz):
# tabs, `?` in flow scalars, `|#`, other line breaks and BOMs. Text with any of them outside
# comments goes to PyYAML's parser: slower, and exactly what the reference loader reads.
_DIVERGENT = re.compile(r"[\t\r\x85\u2028\u2029\ufeff?]|[|>][-+0-9]*#")
_COMMENT = re.compile(r"(?:^|(?<=[ \t]))#[^\n\r\x85\u2028\u2029]*", re.MULTILINE)


def _libyaml_agrees(text: str) -> bool:
    return not _found(_DIVERGENT, text) or not _found(
        _DIVERGENT, "".join(_COMMENT.sub("", text[a:b]) for a, b in _lines_in_pieces(text)))


# A regex call is one C call that keeps the interpreter lock: over a 600 KB download it took
# 4.6 ms, a scan thread waiting meanwhile at 1 ms. In pieces, the lock can change hands.
_PIECE = 32_768


def _lines_in_pieces(text: str) -> list[tuple[int, int]]:
    """(start, end) of pieces of about _PIECE characters, each ending after a newline (or at
    the end): none of the patterns searched here matches across a newline."""
    pieces, start = [], 0
    while start < len(text):
        cut = text.find("\n", start + _PIECE)
        end = len(text) if cut < 0 else cut + 1
        pieces.append((start, end))
        start = end
    return pieces


def _found(pattern: re.Pattern[str], text: str) -> bool:
    return any(pattern.search(text, a, b) is not None for a, b in _lines_in_pieces(text))


class _TooDeep(Exception):
    """The document nests collections deeper than MAX_NESTING."""


class _Unsupported(Exception):
    """What `_build` leaves to the reference loader: explicit tags, bad literals, undefined
    or recursive aliases, several documents, every syntax error (for its exact message)."""


class _Built:
    __slots__ = ("data", "expanded", "own", "problems")

    def __init__(self, data: Any, expanded: int, own: int, problems: list[Problem]) -> None:
        self.data, self.expanded, self.own, self.problems = data, expanded, own, problems


class _Open:
    """A collection being built, its sizes (see _expanded_size) and, in a mapping, the key
    waiting for its value; `skip` marks a rejected key whose value the reference loader
    never constructs: (problems, anchors) counts when the value began."""

    __slots__ = ("anchor", "expanded", "key", "key_line", "own", "skip", "value")

    def __init__(self, value: YMap | YList, anchor: str | None) -> None:
        self.value, self.anchor = value, anchor
        self.expanded = self.own = 1
        self.key: Any = _NO_KEY
        self.key_line = 0
        self.skip: tuple[int, int] | None = None


def _build(source: Any, text: str, filename: str) -> _Built:
    """The reference loader's result for `text`, from a flat walk over the parser's events:
    the same values, lines, problems and sizes; no recursion, so depth is checked as it goes."""
    events = source(text)
    builder = _Builder(filename, libyaml=source is _CParser)
    try:
        return builder.document(events)
    except _Unsupported:
        _drain(events, len(builder.stack))  # a deep document is still refused at once
        raise
    except yaml.YAMLError:
        raise _Unsupported from None
    finally:
        events.dispose()


def _drain(events: Any, depth: int) -> None:
    """Read the rest of the stream for its depth alone."""
    try:
        while (kind := type(events.get_event())) is not yaml.StreamEndEvent:
            if kind in _COLLECTION_TAGS:
                depth += 1
                if depth > MAX_NESTING:
                    raise _TooDeep
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
        self.root: _Built | None = None

    def document(self, events: Any) -> _Built:
        events.get_event()  # stream start
        if type(events.peek_event()) is yaml.StreamEndEvent:
            return _Built(None, 1, 1, [])
        events.get_event()  # document start
        next_event, event = events.get_event, self.event  # bound once: ~10**5 events
        while self.root is None:
            event(next_event())
        events.get_event()  # document end
        if type(events.get_event()) is not yaml.StreamEndEvent:
            raise _Unsupported  # several documents
        return self.root

    def event(self, ev: Any) -> None:
        kind = type(ev)
        if kind is yaml.ScalarEvent:
            if self.libyaml and (ev.tag is not None or (ev.value == "" and self.marked())):
                raise _Unsupported  # libyaml resolves `!` and marks empty scalars otherwise
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
                raise _Unsupported  # undefined, or recursive: the reference loader says which
            self.add(*target)
        else:
            raise _Unsupported

    def marked(self) -> bool:
        """Whether the next value's line is kept: all but a mapping's values."""
        top = self.stack[-1] if self.stack else None
        return top is None or type(top.value) is YList or top.key is _NO_KEY

    def start(self, ev: Any, kind: Any) -> None:
        if ev.tag not in _COLLECTION_TAGS[kind]:
            raise _Unsupported
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
            raise _TooDeep

    def anchor(self, name: str, target: tuple[Any, int, int, int] | None) -> None:
        if name in self.anchors:
            raise _Unsupported  # a duplicate anchor
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
                raise _Unsupported from None
        construct = _SCALARS.get(tag)
        if construct is None:
            raise _Unsupported
        node = yaml.ScalarNode(tag, value, ev.start_mark, ev.end_mark, ev.style)
        try:
            return construct(_SCALAR_CONSTRUCTOR, node)
        except (ValueError, LookupError, AttributeError):
            raise _Unsupported from None

    def add(self, value: Any, line: int, expanded: int, own: int) -> None:
        if not self.stack:
            self.root = _Built(value, expanded, own, self.problems)
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
        problem = _key_problem(top.value, key, line, self.filename)  # type: ignore[arg-type]
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
            raise _Unsupported  # the reference loader builds those at their first alias
        del self.problems[problems:]
        return True


def _unreadable(exc: yaml.YAMLError, text: str, filename: str) -> Problem:
    """One located line for an error without a mark (PyYAML's reader gives a position
    and a multi-line message)."""
    if isinstance(exc, yaml.reader.ReaderError):
        line = text.count("\n", 0, max(exc.position, 0)) + 1
        char = exc.character if isinstance(exc.character, int) else ord(exc.character)
        return Problem(filename, line, "", f"YAML error: character U+{char:04X} is not allowed "
                       "in YAML")
    return Problem(filename, 1, "", "YAML error: " + " ".join(str(exc).split()))


def line_of(container: Any, key: Any, default: int = 0) -> int:
    if isinstance(container, YMap):
        return container.lines.get(key, container.line)
    if isinstance(container, YList) and isinstance(key, int) and key < len(container.lines):
        return container.lines[key]
    return getattr(container, "line", default)


def trap_hint(value: Any) -> str:
    """A hint when a YAML 1.1 boolean word was used where YAML 1.2 reads text."""
    if isinstance(value, str) and value.lower() in YAML11_BOOLS:
        return f" ({value!r} is text here, not a boolean: write true or false)"
    return ""
