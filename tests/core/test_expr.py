"""The sandboxed expression language: what it computes, what it reads, what it refuses.

The sandbox corpus at the end is rejected at compile time; the tests prove that no part of
any rejected text ran (hooks on os.system, open, eval, exec and bytecode compilation, and a
sentinel file that any successful escape would create).
"""

from __future__ import annotations

import ast
import builtins
import os
import subprocess
from pathlib import Path

import pytest

from softplc.core.expr import (
    MAX_NODES,
    MAX_TEXT,
    ExprError,
    NameKind,
    Scope,
    compile_expr,
    names_in,
    substitute,
)
from tests.core.helpers import Ctx

SCOPE = Scope(
    {
        "a": NameKind.BOOL,
        "b": NameKind.BOOL,
        "s1": NameKind.BOOL,
        "w": NameKind.WORD,
        "v": NameKind.WORD,
        "ev": NameKind.EVENT,
        "tok": NameKind.TOKEN,
    },
    consts={"limit": 5, "flag": True},
)
CTX = Ctx(
    {"a": 1, "b": 0, "s1": 1, "w": 7, "v": 3},
    events={"ev"},
    tokens={"tok": {"id": 4, "name": "bolt", "ok": True}},
)


def run(text: str, ctx: Ctx = CTX, scope: Scope = SCOPE) -> object:
    return compile_expr(text, scope)(ctx)


# -- what expressions compute ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("1 + 2 * 3", 7),
        ("(1 + 2) * 3", 9),
        ("w - v - 1", 3),
        ("7 // 2", 3),
        ("-7 // 2", -4),  # floor division, as in Python
        ("7 % 3", 1),
        ("-7 % 3", 2),
        ("6 & 3", 2),
        ("6 | 3", 7),
        ("6 ^ 3", 5),
        ("-w", -7),
        ("+w", 7),
        ("abs(v - w)", 4),
        ("min(w, v)", 3),
        ("max(w, v)", 7),
        ("not a", False),
        ("a and b", False),
        ("a or b", True),
        ("a and not b", True),
        ("w if b else v", 3),
        ("a + a", 2),  # a bool counts as 0/1 in arithmetic
        ("true", True),
        ("false", False),
        ("TRUE", True),
        ("FALSE", False),
        ("True", True),
        ("0x10 + 1_000", 1016),
        ("'bolt' == 'bolt'", True),
        ("'bolt' != 'nut'", True),
        ("ev", True),
        ("w > limit", True),  # a subnet parameter bound to a number
        ("flag and a", True),
        ("9223372036854775807", 2**63 - 1),
    ],
)
def test_operators(text: str, value: object) -> None:
    result = run(text)
    assert result == value
    assert type(result) is type(value)


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("w == 7", True),
        ("w != 7", False),
        ("w < 8", True),
        ("w <= 7", True),
        ("w > 7", False),
        ("w >= 7", True),
        ("v < w", True),
    ],
)
def test_comparisons(text: str, value: bool) -> None:
    assert run(text) is value


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("1 < w < 10", True),
        ("1 < w < 5", False),
        ("v < w > 5", True),
        ("3 == v == 3", True),
        ("0 <= v <= w <= 7", True),
        ("0 <= v <= w < 7", False),
    ],
)
def test_chained_comparisons(text: str, value: bool) -> None:
    assert run(text) is value


def test_token_fields() -> None:
    assert run("tok.id * 2") == 8
    assert run("tok.name == 'bolt'") is True
    assert run("tok.ok and a") is True
    assert run("max(tok.id, w)") == 7


def test_token_field_missing_at_run_time_is_an_error_not_a_value() -> None:
    compiled = compile_expr("tok.weight > 1", SCOPE)
    with pytest.raises(KeyError, match="token bound to 'tok' has no field 'weight'"):
        compiled(CTX)


def test_a_text_constant_is_at_most_256_characters() -> None:
    """Written out, not from MAX_STR: the same bound as a text value (core/values.py)."""
    assert run(f"tok.name != '{'x' * 256}'") is True
    with pytest.raises(ExprError, match=r"^text of 257 characters \(at most 256\)$"):
        compile_expr(f"tok.name == '{'x' * 257}'", SCOPE)


def test_token_fields_can_be_restricted_at_compile_time() -> None:
    scope = Scope({"tok": NameKind.TOKEN}, token_fields={"tok": frozenset({"id"})})
    assert compile_expr("tok.id", scope)(CTX) == 4
    with pytest.raises(ExprError, match="token variable 'tok' has no field 'name'"):
        compile_expr("tok.name", scope)


def test_a_bare_token_variable_needs_a_field() -> None:
    with pytest.raises(ExprError, match=r"token variable 'tok' needs a field, e\.g\. tok\.id"):
        compile_expr("tok", SCOPE)


def test_unknown_name() -> None:
    with pytest.raises(ExprError, match="unknown name 'x': not a symbol, event or token variable"):
        compile_expr("x + 1", SCOPE)


def test_a_yaml_boolean_compiles_as_true_or_false() -> None:
    assert compile_expr(True, SCOPE).text == "true"
    assert compile_expr(False, SCOPE)(CTX) is False


@pytest.mark.parametrize(
    ("text", "error"),
    [
        ("'a' + 'b'", TypeError),  # text takes no part in arithmetic
        ("'a' * 1000000000", TypeError),  # ... so no huge string is ever built
        ("w * 9223372036854775807", OverflowError),  # results are bounded to +-2**63
        ("-9223372036854775807 - w", OverflowError),
        ("'a' < 1", TypeError),
        ("'%s' % w", TypeError),  # %-formatting never runs: text is refused before the op
        ("'{}' * w", TypeError),
    ],
)
def test_run_time_errors_raise_and_the_engine_takes_them_as_false(text: str, error: type) -> None:
    compiled = compile_expr(text, SCOPE)
    with pytest.raises(error):
        compiled(CTX)


# -- edges ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("before", "now", "rising", "falling"),
    [(0, 0, False, False), (0, 1, True, False), (1, 1, False, False), (1, 0, False, True)],
)
def test_rising_and_falling(before: int, now: int, rising: bool, falling: bool) -> None:
    ctx = Ctx({"a": now}, previous={"a": before})
    assert compile_expr("rising(a)", SCOPE)(ctx) is rising
    assert compile_expr("falling(a)", SCOPE)(ctx) is falling


@pytest.mark.parametrize("text", ["rising(w)", "rising(ev)", "rising(tok.id)", "falling(1)",
                                  "rising(a and b)"])
def test_edges_take_the_name_of_a_bool_symbol(text: str) -> None:
    with pytest.raises(ExprError, match=r"rising\(\)/falling\(\) take the name of a bool symbol"):
        compile_expr(text, SCOPE)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("min(1)", r"min\(\) takes 2 positional argument\(s\)"),
        ("abs(1, 2)", r"abs\(\) takes 1 positional argument\(s\)"),
        ("max(a=1, b=2)", r"max\(\) takes 2 positional argument\(s\)"),
        ("rising()", r"rising\(\) takes 1 positional argument\(s\)"),
    ],
)
def test_function_arity(text: str, message: str) -> None:
    with pytest.raises(ExprError, match=message):
        compile_expr(text, SCOPE)


# -- what an expression reads ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "reads", "edges", "tokens"),
    [
        ("a", {"a"}, set(), set()),
        ("rising(a) and w > 3", {"a", "w"}, {"a"}, set()),
        ("falling(b) or ev", {"b", "ev"}, {"b"}, set()),
        ("tok.id == v", {"v"}, set(), {"tok"}),
        ("w > limit", {"w"}, set(), set()),  # a constant is no read
        ("1 + 2", set(), set(), set()),
        ("true", set(), set(), set()),
    ],
)
def test_reads_edges_and_tokens(text: str, reads: set[str], edges: set[str],
                                tokens: set[str]) -> None:
    compiled = compile_expr(text, SCOPE)
    assert compiled.reads == reads
    assert compiled.edges == edges
    assert compiled.tokens == tokens


def test_names_in_and_substitute_work_on_the_syntax_tree() -> None:
    assert names_in("sensor and not rising(x) and sensor2") == {"sensor", "rising", "x", "sensor2"}
    assert names_in("this is not ( valid") == set()
    # a text value renames a name, a number or bool becomes a literal; strings are untouched
    assert substitute("sensor and w > limit and 'sensor' == 'sensor'",
                      {"sensor": "s1_i", "limit": 3}) == \
        "s1_i and w > 3 and ('sensor' == 'sensor')"


# -- the sandbox ----------------------------------------------------------------------------

NOT_CALLABLE = ("only these functions may be called: abs, dint, falling, int, lreal, max, min, "
                "real, rising, trunc, udint, word")
NO_ATTRIBUTE = "attribute access is only allowed as <token variable>.<field>"

ESCAPES: list[tuple[str, str]] = [
    ("__import__('os').system('x')", NOT_CALLABLE),
    ("().__class__.__bases__", NO_ATTRIBUTE),
    ("().__class__.__base__.__subclasses__()", NOT_CALLABLE),
    ("s1.__class__", NO_ATTRIBUTE),
    ("w.real", NO_ATTRIBUTE),
    ("a.b.c", NO_ATTRIBUTE),
    ("tok.id.__class__", NO_ATTRIBUTE),
    ("tok.id.bit_length", NO_ATTRIBUTE),
    ("tok.__class__", "field '__class__' is not allowed (no leading underscore)"),
    ("tok._private", "field '_private' is not allowed (no leading underscore)"),
    ("'x'.join", NO_ATTRIBUTE),
    ("rising(a).__class__", NO_ATTRIBUTE),
    ("min.__call__(1, 2)", NOT_CALLABLE),
    ("(lambda: 1)()", NOT_CALLABLE),
    ("lambda: 1", "lambda is not allowed in an expression"),
    ("[x for x in (1, 2)]", "a comprehension is not allowed in an expression"),
    ("{x for x in (1, 2)}", "a comprehension is not allowed in an expression"),
    ("{x: 1 for x in (1, 2)}", "a comprehension is not allowed in an expression"),
    ("max(x for x in (1, 2))", "max() takes 2 positional argument(s)"),
    ("abs(x for x in (1, 2))", "a generator is not allowed in an expression"),
    ("a[0]", "subscript [] is not allowed in an expression"),
    ("tok['id']", "subscript [] is not allowed in an expression"),
    ("'abc'[0]", "subscript [] is not allowed in an expression"),
    ("f'{a}'", "an f-string is not allowed in an expression"),
    ("(x := 1)", "assignment := is not allowed in an expression"),
    ("abs(*a)", "*unpacking is not allowed in an expression"),
    ("max(**a)", "max() takes 2 positional argument(s)"),
    ("2 ** 10 ** 10", "operator ** is not allowed"),
    ("w ** 2", "operator ** is not allowed"),
    ("1 << 100", "operator << is not allowed"),
    ("w >> 1", "operator >> is not allowed"),
    ("~w", "operator ~ is not allowed; use 'not' or arithmetic"),
    ("w in (1, 2)", "comparison In is not allowed"),
    ("a is b", "comparison Is is not allowed"),
    ("pow(2, 10)", NOT_CALLABLE),
    ("open('x')", NOT_CALLABLE),
    ("eval('1')", NOT_CALLABLE),
    ("exec('1')", NOT_CALLABLE),
    ("compile('1', '', 'eval')", NOT_CALLABLE),
    ("getattr(a, 'x')", NOT_CALLABLE),
    ("globals()", NOT_CALLABLE),
    ("vars()", NOT_CALLABLE),
    ("type(a)", NOT_CALLABLE),
    ("breakpoint()", NOT_CALLABLE),
    ("a if a else __import__('os')", NOT_CALLABLE),
    ("__builtins__", "name '__builtins__' is not allowed (no leading underscore)"),
    ("__import__", "name '__import__' is not allowed (no leading underscore)"),
    ("_", "name '_' is not allowed (no leading underscore)"),
    ("[1, 2]", "a list is not allowed in an expression"),
    ("(1, 2)", "a tuple is not allowed in an expression"),
    ("{1: 2}", "a dict is not allowed in an expression"),
    ("{1}", "a set is not allowed in an expression"),
    ("1e999", "constant inf is not a finite number"),
    ("None", "constant None is not allowed: use numbers, true/false or 'text'"),
    ("b'x'", "constant b'x' is not allowed: use numbers, true/false or 'text'"),
    ("...", "constant Ellipsis is not allowed: use numbers, true/false or 'text'"),
    ("1j", "constant 1j is not allowed: use numbers, true/false or 'text'"),
    ("await a", "await is not allowed in an expression"),
    ("import os", "syntax error: invalid syntax"),
    ("a; b", "syntax error: invalid syntax"),
    ("w = 1 = 2 = (x := 3)", "assignment := is not allowed in an expression"),
    ("w += 1", "syntax error: invalid syntax"),
    ("yield 1", "syntax error: invalid syntax"),
    ("(" * 300 + "1" + ")" * 300, "syntax error: too many nested parentheses"),
    ("not " * 450 + "a", "expression too complex (903 nodes, at most 400)"),
    ("-" * 1999 + "1", "expression too complex (4000 nodes, at most 400)"),
    ("+".join(["w"] * 300), "expression too complex"),
    ("1" * (MAX_TEXT + 1), f"expression longer than {MAX_TEXT} characters"),
    # Unicode names are NFKC-normalised by the parser: fullwidth letters are plain names.
    ("\uff45\uff56\uff41\uff4c('1')", NOT_CALLABLE),
    ("\uff3f\uff3fimport\uff3f\uff3f('os')", "syntax error: invalid character"),
    # format-string tricks reach attributes through str.format / %
    ("'{0.__class__}'.format(a)", NOT_CALLABLE),
    ("'{}'.format", NO_ATTRIBUTE),
    ("'%(x)s' % {'x': 1}", "a dict is not allowed in an expression"),
    ("f'{a!r}'", "an f-string is not allowed in an expression"),
    ("f'{a:{b}}'", "an f-string is not allowed in an expression"),
    ("rf'{a}'", "an f-string is not allowed in an expression"),
    # lambda defaults, generator frames, code objects, bound builtins
    ("(lambda x=__import__('os'): x)()", NOT_CALLABLE),
    ("(lambda: 1).__code__", NO_ATTRIBUTE),
    ("(x for x in ()).gi_frame", NO_ATTRIBUTE),
    ("abs.__self__", NO_ATTRIBUTE),
    ("min(a, b).__class__", NO_ATTRIBUTE),
    ("True.__class__", NO_ATTRIBUTE),
    ("[].__class__", NO_ATTRIBUTE),
    ("{}.get", NO_ATTRIBUTE),
    ("a.__dict__", NO_ATTRIBUTE),
    ("a.__getattribute__('x')", NOT_CALLABLE),
    ("tok.__globals__", "field '__globals__' is not allowed (no leading underscore)"),
    ("tok.id.__class__.__subclasses__()", NOT_CALLABLE),
    ("tok.id.real", NO_ATTRIBUTE),
    ("super()", NOT_CALLABLE),
    ("setattr(a, 'x', 1)", NOT_CALLABLE),
    ("locals()", NOT_CALLABLE),
    ("print(1)", NOT_CALLABLE),
    ("__debug__", "name '__debug__' is not allowed (no leading underscore)"),
    ("__loader__", "name '__loader__' is not allowed (no leading underscore)"),
    ("type", "unknown name 'type': not a symbol, event or token variable"),
    ("object", "unknown name 'object': not a symbol, event or token variable"),
    # yield/await and scope tricks inside otherwise valid expressions
    ("(yield)", "yield is not allowed in an expression"),
    ("(yield from a)", "YieldFrom is not allowed in an expression"),
    ("1 if a else (yield)", "yield is not allowed in an expression"),
    ("x if (y := 1) else 2", "assignment := is not allowed in an expression"),
    ("[a for a in ()] if a else 1", "a comprehension is not allowed in an expression"),
    ("[*a]", "a list is not allowed in an expression"),
    ("{**a}", "a dict is not allowed in an expression"),
    ("(a, *b)", "a tuple is not allowed in an expression"),
    ("a[::-1]", "subscript [] is not allowed in an expression"),
    ("a @ b", "operator MatMult is not allowed"),
    ("rb'x'", "constant b'x' is not allowed: use numbers, true/false or 'text'"),
    ("9" * 100, "integer 9999"),
    ("not " * 199 + "a", "expression too complex (401 nodes, at most 400)"),
]


@pytest.mark.parametrize(("text", "message"), ESCAPES, ids=[t[:40] for t, _ in ESCAPES])
def test_escape_is_rejected_at_compile_time(text: str, message: str) -> None:
    with pytest.raises(ExprError) as info:
        compile_expr(text, SCOPE)
    assert info.value.message.startswith(message)


def test_limits_are_as_documented() -> None:
    assert (MAX_NODES, MAX_TEXT) == (400, 2000)
    compile_expr("(" * 150 + "w" + ")" * 150, SCOPE)  # deep but small: accepted
    compile_expr(" + ".join(["w"] * 100), SCOPE)


def payloads(sentinel: Path) -> list[str]:
    """Escape attempts that, if any part of them ran, would create `sentinel`."""
    s = repr(str(sentinel))
    return [
        f"__import__('os').system('touch ' + {s})",
        f"open({s}, 'w')",
        f"exec(\"open({s}, 'w')\")",
        f"eval(\"open({s}, 'w')\")",
        f"[open({s}, 'w') for _ in (1,)]",
        f"(lambda: open({s}, 'w'))()",
        f"__builtins__.open({s}, 'w')",
        f"getattr(__builtins__, 'open')({s}, 'w')",
        f"f\"{{open({s}, 'w')}}\"",
        f"(x := open({s}, 'w'))",
        f"a[open({s}, 'w')]",
        f"a if open({s}, 'w') else b",
        f"min(open({s}, 'w'), 1)",
        f"tok.__class__.__init__.__globals__['__builtins__']['open']({s}, 'w')",
        f"().__class__.__base__.__subclasses__()[0]({s})",
        f"2 ** 10 ** 10 ** 10 and open({s}, 'w')",
        f"__import__('subprocess').run(['touch', {s}])",
        f"\uff4f\uff50\uff45\uff4e({s}, 'w')",
        f"'{{0.__init__.__globals__}}'.format(open({s}, 'w'))",
        f"(lambda f=open({s}, 'w'): f)()",
        f"min(w, 1) if (f := open({s}, 'w')) else 0",
    ]


class Forbidden(Exception):
    pass


def test_nothing_of_a_rejected_text_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sentinel = tmp_path / "pwned"
    calls: list[str] = []

    def trap(name: str):  # type: ignore[no-untyped-def]
        def hook(*args: object, **kwargs: object) -> None:
            calls.append(name)
            raise Forbidden(name)

        return hook

    real_compile = builtins.compile

    def only_ast(source, filename, mode, flags=0, *args, **kwargs):  # type: ignore[no-untyped-def]
        # ast.parse is allowed (it builds a tree); compiling program text to bytecode is not
        if not flags & ast.PyCF_ONLY_AST:
            calls.append(f"compile({mode})")
            raise Forbidden("compile")
        return real_compile(source, filename, mode, flags, *args, **kwargs)

    monkeypatch.setattr(os, "system", trap("os.system"))
    monkeypatch.setattr(subprocess, "run", trap("subprocess.run"))
    monkeypatch.setattr(subprocess, "Popen", trap("subprocess.Popen"))
    monkeypatch.setattr(builtins, "open", trap("open"))
    monkeypatch.setattr(builtins, "eval", trap("eval"))
    monkeypatch.setattr(builtins, "exec", trap("exec"))
    monkeypatch.setattr(builtins, "compile", only_ast)
    rejected = 0
    for text in payloads(sentinel):
        try:
            compile_expr(text, SCOPE)
        except ExprError:
            rejected += 1
    monkeypatch.undo()
    assert rejected == len(payloads(sentinel))
    assert calls == []
    assert not sentinel.exists()


def test_accepted_expressions_run_without_eval_or_bytecode(monkeypatch: pytest.MonkeyPatch) -> None:
    """Program text is parsed to a tree and turned into closures; it is never compiled to
    bytecode nor evaluated, even when it is valid."""
    compiled_modes: list[str] = []
    real_compile = builtins.compile

    def spy(source, filename, mode, flags=0, *args, **kwargs):  # type: ignore[no-untyped-def]
        if not flags & ast.PyCF_ONLY_AST:
            compiled_modes.append(mode)
        return real_compile(source, filename, mode, flags, *args, **kwargs)

    monkeypatch.setattr(builtins, "compile", spy)
    monkeypatch.setattr(builtins, "eval", lambda *a, **k: pytest.fail("eval called"))
    fn = compile_expr("rising(a) or (w > limit and tok.id == 4 and abs(v - w) >= 4)", SCOPE)
    assert fn(Ctx({"w": 7, "v": 3}, tokens={"tok": {"id": 4}})) is True
    assert compiled_modes == []


@pytest.mark.parametrize("text", ["99999999999999999999", "w > 99999999999999999999",
                                  "-9223372036854775808"])
def test_huge_integer_literal_is_an_expression_error(text: str) -> None:
    with pytest.raises(ExprError):
        compile_expr(text, SCOPE)


@pytest.mark.parametrize("text", ["7 // 0", "7 % 0", "w // (v - 3)", "w % (v - 3)"])
def test_division_by_zero_is_a_run_time_error_the_engine_reports(text: str) -> None:
    """Not a silent 0 (issue 16): the engine turns it into a located diagnostic."""
    with pytest.raises(ZeroDivisionError):
        run(text)


# -- IEC 61131-3 operator words (core/iecwords.py, docs/programs.md "Expressions") ----------


@pytest.mark.parametrize(
    ("text", "value"),
    [
        ("a AND NOT b", True),
        ("a AND b OR s1", True),
        ("NOT a OR b", False),
        ("NOT a = b", True),  # IEC: (NOT a) = b; NOT binds tighter than a comparison
        ("NOT (w > 3)", False),
        ("w > 3 AND v < 4", True),
        ("Not a Or b", False),  # IEC is case-insensitive; capitalised words too
        ("w MOD 4", 3),
        ("-7 MOD 3", -1),  # IEC: the dividend's sign (Python's % gives 2)
        ("7 MOD -3", 1),
        ("w MOD 4 * 2", 6),  # MOD binds like *
        ("'AND' == 'AND' AND a", True),  # words in text are text
        ("tok.ok AND a", True),
    ],
)
def test_iec_words_read_with_iec_meaning(text: str, value: object) -> None:
    assert run(text) == value


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("a XOR b", "XOR is not in the language (no operator has its IEC precedence): for bools "
                    "write a != b, for integer bits a ^ b"),
        ("NOT w", "NOT of 'w' (int): IEC's NOT of an integer is bitwise, here NOT is logical and "
                  "takes bools; compare instead, e.g. w <> 0"),
        ("w AND a", "AND of 'w' (int): IEC's AND of an integer is bitwise"),
        ("a OR 2.5", "OR of '2.5' (float)"),
        ("a @ b", "operator MatMult is not allowed"),  # `@` is still not the user's to write
        ("~a", "operator ~ is not allowed"),
    ],
)
def test_iec_words_that_would_change_meaning_are_refused_with_a_hint(text: str,
                                                                     message: str) -> None:
    with pytest.raises(ExprError) as err:
        compile_expr(text, SCOPE)
    assert message in err.value.message


def test_a_substituted_iec_expression_keeps_its_meaning() -> None:
    text = substitute("NOT sensor AND w MOD limit = 1", {"sensor": "b", "limit": 3})
    assert run(text) is True and "NOT" in text and "MOD" in text
    assert names_in("NOT sensor AND x") == {"sensor", "x"}


def test_iec_comparisons_equal_and_not_equal() -> None:
    assert run("w = 7 AND v <> 7") is True
    assert run("w<>7") is False
    with pytest.raises(ExprError, match="syntax error"):
        compile_expr("w < > 7", SCOPE)  # <> is one operator: no space inside


def test_a_bool_symbol_reads_as_true_or_false_not_as_its_raw_bit() -> None:
    """Issue 43: a BOOL symbol stored as 1 is True (an action's `b == True`, a text made of
    it), a WORD stored as 1 stays 1."""
    assert run("a") is True and run("b") is False
    assert run("a == True") is True and run("w") == 7
    ctx = Ctx({"a": 1, "w": 1})
    assert run("a", ctx) is True and run("w", ctx) == 1 and run("w", ctx) is not True
