"""The ST subset of conditions and action bodies -> softplc's expression language.

Owns: the tokenizer and a recursive-descent parser of IEC 61131-3 ST expressions (with ST's
precedence: NOT and unary minus, * / MOD, + -, < > <= >=, = <>, AND &, XOR, OR), typed
translation into a fully parenthesised softplc expression (so Python's precedence and chained
comparisons never change the meaning), assignments `X := expr;`, and the located refusal of
anything else. Steps' `S.X` and `S.T` come out as Flag nodes for the caller to place.
Does not know: XML, nets. Never evaluates anything: the text it writes goes through
softplc's sandboxed compiler (core/expr.py) like any YAML guard.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from softplc.core.errors import SoftplcError
from softplc.core.units import parse_duration_ns
from softplc.sfc import fbs

# IEC types softplc reads, by the kind the translation checks operands with.
BOOL, INT, REAL, TIME = "bool", "int", "real", "time"
STEP_X = "__X_"  # `S1.X` in a body: TRUE or FALSE where the body runs (emit.py)

_TOKEN = re.compile(r"""
    (?P<ws>\s+|\(\*.*?\*\)|//[^\n]*)
  | (?P<time>(?:T|TIME)\#-?[0-9_.a-zA-Z]+)
  | (?P<num>\d[\d_]*\#[0-9A-Fa-f_]+|\d[\d_]*\.\d[\d_]*(?:[eE][+-]?\d+)?|\d[\d_]*(?:[eE][+-]?\d+)?)
  | (?P<id>[A-Za-z_][A-Za-z0-9_]*(?:\.[A-Za-z_][A-Za-z0-9_]*)?)
  | (?P<op>:=|<>|<=|>=|\*\*|[-+*/()<>=&,;])
""", re.VERBOSE | re.DOTALL | re.IGNORECASE)
SUPPORTED = ("ST supported: TRUE/FALSE, numbers, TIME literals (T#5s), variables, Step.X/Step.T, "
             "NOT, AND/&, OR, XOR, = <> < > <= >=, + - * /, parentheses, AND()/OR()/XOR()/"
             "NOT()/ABS()/MIN()/MAX()/SEL()/LIMIT(), FB outputs T1.Q, and `X := expr;` and "
             "calls `T1(IN := x, PT := T#5s);` (TON, TOF, TP, R_TRIG, F_TRIG) in action bodies")


class StError(SoftplcError, ValueError):
    """A construct outside the subset; `offset` is where in the text it starts."""

    def __init__(self, message: str, offset: int) -> None:
        super().__init__(message, offset)
        self.message, self.offset = message, offset


@dataclass(frozen=True, slots=True)
class Tok:
    kind: str  # time, num, id, op, end
    text: str
    offset: int


@dataclass(frozen=True, slots=True)
class Flag:
    """`Step.X` (active) or `Step.T` (time since activation) of the chart's step `step`."""

    step: str
    flag: str  # "X" or "T"
    offset: int


@dataclass(frozen=True, slots=True)
class Node:
    op: str  # lit, var, not, neg, call, or an ST binary operator (upper case)
    args: tuple[Node | Flag, ...] = ()
    text: str = ""  # lit: softplc text; var: the declared name; call: the function
    kind: str = ""
    offset: int = 0


Expr = Node | Flag


def tokens(text: str) -> list[Tok]:
    out, pos = [], 0
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None:
            raise StError(f"unexpected {text[pos:pos + 10]!r}", pos)
        if m.lastgroup != "ws":
            out.append(Tok(str(m.lastgroup), m.group(), pos))
        pos = m.end()
    out.append(Tok("end", "", len(text)))
    return out


def time_ms(text: str, offset: int = 0) -> int:
    """`T#1h2m3s4ms`, `TIME#1.5s`, `t#250ms`, `10s`, `T#-5s` (ST allows a sign) -> milliseconds;
    below 1 ms refused. The spelling is core/units.py's, the one reader of durations."""
    prefix, _, body = text.rpartition("#")
    sign = -1 if body.startswith("-") else 1
    unsigned = f"{prefix}#{body[1:]}" if sign < 0 else text
    try:
        ns = parse_duration_ns(unsigned)
    except ValueError:
        raise StError(f"TIME literal {text!r} is not of the form T#1h2m3s4ms", offset) from None
    if ns % 1_000_000:
        raise StError(f"TIME literal {text!r} is finer than a millisecond", offset)
    return sign * (ns // 1_000_000)


class Parser:
    """One ST text. `names` maps an identifier (upper case) to (declared name, kind); `steps`
    maps a step name (upper case) to its declared name."""

    def __init__(self, text: str, names: Mapping[str, tuple[str, str]],
                 steps: Mapping[str, str]) -> None:
        self.toks, self.i = tokens(text), 0
        self.names, self.steps = names, steps
        self.body = False  # an action body: Step.X is a marker emit.py resolves (STEP_X)

    @property
    def tok(self) -> Tok:
        return self.toks[self.i]

    def take(self, *words: str) -> Tok | None:
        if self.tok.text.upper() in words and self.tok.kind in ("op", "id"):
            self.i += 1
            return self.toks[self.i - 1]
        return None

    def expect(self, word: str) -> None:
        if self.take(word) is None:
            raise StError(f"expected {word!r}, found {self.tok.text or 'the end'!r}",
                          self.tok.offset)

    def expression(self) -> Expr:
        return self._binary(0)

    _LEVELS = (("OR",), ("XOR",), ("AND", "&"), ("=", "<>"), ("<", ">", "<=", ">="),
               ("+", "-"), ("*", "/", "MOD"), ("**",))

    def _binary(self, level: int) -> Expr:
        if level == len(self._LEVELS):
            return self._unary()
        left = self._binary(level + 1)
        while (tok := self.take(*self._LEVELS[level])) is not None:
            op = "AND" if tok.text == "&" else tok.text.upper()
            left = Node(op, (left, self._binary(level + 1)), offset=tok.offset)
        return left

    def _unary(self) -> Expr:
        if (tok := self.take("NOT", "-", "+")) is not None:
            inner = self._unary()
            if tok.text == "+":
                return inner
            return Node("not" if tok.text.upper() == "NOT" else "neg", (inner,),
                        offset=tok.offset)
        return self._primary()

    def _primary(self) -> Expr:
        tok = self.tok
        self.i += 1
        if tok.text == "(":
            inner = self.expression()
            self.expect(")")
            return inner
        if tok.kind == "time":
            return Node("lit", text=str(time_ms(tok.text, tok.offset)), kind=TIME,
                        offset=tok.offset)
        if tok.kind == "num":
            return _number(tok)
        if tok.kind == "id":
            return self._name(tok)
        raise StError(f"unexpected {tok.text or 'end of text'!r}", tok.offset)

    def _name(self, tok: Tok) -> Expr:
        word = tok.text.upper()
        if word in ("TRUE", "FALSE"):
            return Node("lit", text=word.lower(), kind=BOOL, offset=tok.offset)
        if self.tok.text == "(":
            if word in self.names and self.names[word][1].startswith("fb"):
                raise StError(f"{tok.text}(...): a function block call is a statement; call "
                              f"it in an action body and read {tok.text}.Q here", tok.offset)
            self.i += 1
            args = [self.expression()]
            while self.take(","):
                args.append(self.expression())
            self.expect(")")
            return Node("call", tuple(args), text=word, offset=tok.offset)
        if "." in word:
            step, _, flag = word.partition(".")
            if step in self.steps and flag == "X" and self.body:
                return Node("var", text=STEP_X + self.steps[step], kind=BOOL, offset=tok.offset)
            if step in self.steps and flag in ("X", "T"):
                return Flag(self.steps[step], flag, tok.offset)
            if step in self.names and self.names[step][1].startswith("fb"):
                try:
                    sym = fbs.output(*self.names[step], flag, tok.offset)
                except fbs.FbError as exc:
                    raise StError(exc.message, exc.offset) from None
                return Node("var", text=sym, kind=BOOL, offset=tok.offset)
            raise StError(f"{tok.text!r}: only the step flags Step.X and Step.T may be "
                          "dotted (no structure or function block fields)", tok.offset)
        if word not in self.names:
            raise StError(f"unknown variable {tok.text!r}: declare it in the POU's interface "
                          "or the configuration's globals", tok.offset)
        name, kind = self.names[word]
        if kind.startswith("fb"):
            raise StError(f"{tok.text!r} is a function block instance: read its output "
                          f"{tok.text}.Q; supported: {fbs.SUPPORTED}", tok.offset)
        return Node("var", text=name, kind=kind, offset=tok.offset)

    def at_end(self) -> None:
        if self.tok.kind != "end":
            raise StError(f"unexpected {self.tok.text!r} after the expression", self.tok.offset)


def _number(tok: Tok) -> Node:
    text = tok.text.replace("_", "")
    if "#" in text:
        base, _, digits = text.partition("#")
        if base not in ("2", "8", "16"):
            raise StError(f"number {tok.text!r}: base must be 2, 8 or 16", tok.offset)
        return Node("lit", text=str(int(digits, int(base))), kind=INT, offset=tok.offset)
    is_real = "." in text or "e" in text.lower()
    return Node("lit", text=repr(float(text)) if is_real else str(int(text)),
                kind=REAL if is_real else INT, offset=tok.offset)


def parse_condition(text: str, names: Mapping[str, tuple[str, str]],
                    steps: Mapping[str, str]) -> Expr:
    """A transition condition; a named transition's body `[NAME] := expr;` reads the same."""
    head = re.match(r"\s*([A-Za-z_]\w*)?\s*:=", text)
    if head is not None:  # blanked, not cut: offsets (and so lines) stay those of the file
        text = " " * head.end() + text[head.end():]
    body = text.rstrip()
    if body.endswith(";"):
        text = body[:-1]
    parser = Parser(text, names, steps)
    expr = parser.expression()
    parser.at_end()
    return expr


def parse_statements(text: str, names: Mapping[str, tuple[str, str]],
                     steps: Mapping[str, str]) -> list[tuple[str, str, Expr, int]]:
    """`X := expr;` ... -> [(declared X, X's kind, expr, offset)]; anything else refused."""
    parser, out = Parser(text, names, steps), []
    parser.body = True
    while parser.tok.kind != "end":
        if parser.take(";"):
            continue
        tok = parser.tok
        fb = parser.names.get(tok.text.upper(), ("", ""))[1].startswith("fb")
        if tok.kind == "id" and fb and parser.toks[parser.i + 1].text == "(":
            out.extend(_fb_call(parser, tok))
            if parser.tok.kind != "end":
                parser.expect(";")
            continue
        if tok.kind != "id" or parser.toks[parser.i + 1].text != ":=":
            raise StError(f"statement starting {tok.text!r} is not supported: action bodies "
                          "may only hold assignments `X := expr;` and calls of function "
                          f"blocks ({fbs.SUPPORTED}); no IF, CASE or loops", tok.offset)
        if tok.text.upper() not in parser.names:
            raise StError(f"unknown variable {tok.text!r}", tok.offset)
        name, kind = parser.names[tok.text.upper()]
        parser.i += 2
        out.append((name, kind, parser.expression(), tok.offset))
        if parser.tok.kind != "end":
            parser.expect(";")
    return out


def _fb_call(parser: Parser, tok: Tok) -> list[tuple[str, str, Expr, int]]:
    """`T1(IN := expr, PT := T#5s)` (formal arguments, any order) -> the statements it is."""
    inst, kind = parser.names[tok.text.upper()]
    parser.i += 2
    args: dict[str, tuple[str, str, int]] = {}
    while parser.take(")") is None:
        if args:
            parser.expect(",")
        p = parser.tok
        if p.kind != "id" or parser.toks[parser.i + 1].text != ":=":
            raise StError(f"{inst}(...): arguments must be formal, `IN := expr` (positional "
                          "arguments and output bindings `=>` are not supported)", p.offset)
        parser.i += 2
        args[p.text.upper()] = (*emit(parser.expression()), p.offset)
    try:
        stmts = fbs.expand(inst, kind, args, tok.offset)
    except fbs.FbError as exc:
        raise StError(exc.message, exc.offset) from None
    return [(t, k, Node("lit", text=x, kind=k, offset=tok.offset), tok.offset)
            for t, k, x in stmts]


def emit(expr: Expr) -> tuple[str, str]:
    """(softplc expression text, kind). Flags are the caller's to remove first."""
    if isinstance(expr, Flag):
        raise StError(f"{expr.step}.{expr.flag} may only stand in a condition's top-level AND "
                      f"({expr.step}.X, NOT {expr.step}.X) or alone as "
                      f"`{expr.step}.T >= T#...`", expr.offset)
    if expr.op in ("lit", "var"):
        return expr.text, expr.kind
    if expr.op == "call":
        return _call(expr)
    parts = [emit(a) for a in expr.args]
    return _OPS.get(expr.op, _refused)(expr, parts)


def _refused(expr: Node, parts: list[tuple[str, str]]) -> tuple[str, str]:
    why = {"MOD": "MOD truncates toward zero in ST and floors in softplc; not translated",
           "**": "EXPT/** is not supported"}
    raise StError(why.get(expr.op, f"operator {expr.op} is not supported"), expr.offset)


def _need(expr: Node, parts: list[tuple[str, str]], kinds: tuple[str, ...]) -> None:
    for text, kind in parts:
        if kind not in kinds:
            wanted = " or ".join(k.upper() for k in kinds)
            raise StError(f"{expr.op} of {text} ({kind.upper()}): expected {wanted}"
                          + (" (AND/OR/NOT of integers are bitwise in ST: not supported)"
                             if kind == INT and BOOL in kinds else ""), expr.offset)


def _logic(word: str) -> Callable[[Node, list[tuple[str, str]]], tuple[str, str]]:
    def build(expr: Node, parts: list[tuple[str, str]]) -> tuple[str, str]:
        _need(expr, parts, (BOOL,))
        if word == "not":
            return f"(not {parts[0][0]})", BOOL
        return "(" + f" {word} ".join(p[0] for p in parts) + ")", BOOL
    return build


def _compare(py: str) -> Callable[[Node, list[tuple[str, str]]], tuple[str, str]]:
    def build(expr: Node, parts: list[tuple[str, str]]) -> tuple[str, str]:
        kinds = {k for _, k in parts}
        bool_01 = BOOL in kinds and all(k == BOOL or t in ("0", "1") for t, k in parts)
        if py in ("==", "!=") and (kinds == {BOOL} or bool_01):
            return f"({parts[0][0]} {py} {parts[1][0]})", BOOL
        _need(expr, parts, (INT, REAL) if TIME not in kinds else (TIME,))
        return f"({parts[0][0]} {py} {parts[1][0]})", BOOL
    return build


def _arith(py: str) -> Callable[[Node, list[tuple[str, str]]], tuple[str, str]]:
    def build(expr: Node, parts: list[tuple[str, str]]) -> tuple[str, str]:
        kinds = {k for _, k in parts}
        if TIME in kinds:
            if py in ("+", "-") and kinds == {TIME}:
                return f"({parts[0][0]} {py} {parts[1][0]})", TIME
            if py in ("*", "/") and parts[0][1] == TIME and parts[1][1] == INT:
                text = f"({parts[0][0]} * {parts[1][0]})" if py == "*" else \
                    f"trunc({parts[0][0]} / {parts[1][0]})"
                return text, TIME
        _need(expr, parts, (INT, REAL))
        kind = REAL if REAL in kinds else INT
        if py == "/" and kind == INT:  # ST's integer division truncates toward zero
            return f"trunc({parts[0][0]} / {parts[1][0]})", INT
        return f"({parts[0][0]} {py} {parts[1][0]})", kind
    return build


def _neg(expr: Node, parts: list[tuple[str, str]]) -> tuple[str, str]:
    _need(expr, parts, (INT, REAL, TIME))
    return f"(-{parts[0][0]})", parts[0][1]


_OPS: dict[str, Callable[[Node, list[tuple[str, str]]], tuple[str, str]]] = {
    "OR": _logic("or"), "AND": _logic("and"), "not": _logic("not"), "neg": _neg,
    "XOR": lambda e, p: _call(Node("call", e.args, text="XOR", offset=e.offset)),
    "=": _compare("=="), "<>": _compare("!="), "<": _compare("<"), ">": _compare(">"),
    "<=": _compare("<="), ">=": _compare(">="),
    "+": _arith("+"), "-": _arith("-"), "*": _arith("*"), "/": _arith("/"),
}


def _call(expr: Node) -> tuple[str, str]:
    name, parts = expr.text, [emit(a) for a in expr.args]
    arity = {"NOT": 1, "ABS": 1, "SEL": 3, "LIMIT": 3}
    if name in arity and len(parts) != arity[name]:
        raise StError(f"{name}() takes {arity[name]} argument(s)", expr.offset)
    if name in ("AND", "OR", "XOR") and len(parts) >= 2:
        if name == "XOR":
            _need(expr, parts, (BOOL,))
            text = parts[0][0]
            for p in parts[1:]:
                text = f"({text} != {p[0]})"
            return text, BOOL
        return _logic(name.lower())(expr, parts)
    if name == "NOT":
        return _logic("not")(expr, parts)
    if name == "ABS":
        _need(expr, parts, (INT, REAL, TIME))
        return f"abs({parts[0][0]})", parts[0][1]
    if name in ("MIN", "MAX") and len(parts) >= 2:
        _need(expr, parts, (INT, REAL) if parts[0][1] != TIME else (TIME,))
        text = parts[0][0]
        for p in parts[1:]:
            text = f"{name.lower()}({text}, {p[0]})"
        return text, REAL if any(k == REAL for _, k in parts) else parts[0][1]
    if name == "SEL":
        _need(expr, parts[:1], (BOOL,))
        return f"({parts[2][0]} if {parts[0][0]} else {parts[1][0]})", parts[1][1]
    if name == "LIMIT":
        return f"min(max({parts[1][0]}, {parts[0][0]}), {parts[2][0]})", parts[1][1]
    raise StError(f"function {name}() is not supported; " + SUPPORTED, expr.offset)
