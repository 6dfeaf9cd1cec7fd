"""IEC 61131-3 operator words in expressions: `AND`, `OR`, `NOT`, `MOD` read, `XOR` hinted.

Owns: the token-level rewrite that runs before `ast.parse` (core/expr.py): outside strings,
the upper-case (or capitalised) words AND/OR become `and`/`or`, NOT becomes `~` and MOD `@`,
IEC's comparisons `=` and `<>` become `==` and `!=`;
two operators the language has no other use for, so the compiler gives them IEC's meaning
with IEC's precedence (NOT binds tightest, MOD as `*`). XOR has no Python operator at its
IEC precedence (between AND and OR), so it is refused with the spelling to use instead.
Does not know: scopes, kinds (the compiler checks that AND/OR/NOT got bools).
"""

from __future__ import annotations

import io
import tokenize

__all__ = ["IEC_WORDS", "XOR_HINT", "rewrite", "unrewrite"]

_TO_PYTHON = {"AND": "and", "OR": "or", "NOT": "~", "MOD": "@"}
IEC_WORDS = frozenset({*_TO_PYTHON, "XOR"})


XOR_HINT = ("XOR is not in the language (no operator has its IEC precedence): for bools "
            "write a != b, for integer bits a ^ b")


def _tokens(text: str) -> list[tokenize.TokenInfo] | None:
    try:
        return list(tokenize.generate_tokens(io.StringIO(text).readline))
    except (tokenize.TokenError, SyntaxError):
        return None  # ast.parse reports it with its own message


def _offsets(text: str) -> list[int]:
    starts, total = [0], 0
    for line in text.splitlines(keepends=True):
        total += len(line)
        starts.append(total)
    return starts


def rewrite(text: str) -> tuple[str, frozenset[str]]:
    """(`text` with its IEC words in Python's spelling, the IEC words it used).
    XOR among the words means: refuse it with XOR_HINT. Words in strings, after a `.` (a
    token field) or in lower case are kept."""
    tokens = _tokens(text)
    if tokens is None:
        return text, frozenset()
    starts = _offsets(text)
    edits: list[tuple[int, int, str]] = []
    used: set[str] = set()
    previous = ""
    for i, tok in enumerate(tokens):
        word = tok.string
        after = tokens[i + 1] if i + 1 < len(tokens) else tok
        keyword = (i >= 2 and tokens[i - 1].type == tokenize.NAME
                   and tokens[i - 2].string in ("(", ",", "lambda"))
        if tok.type == tokenize.OP and ((word == "=" and not keyword) or (
                word == "<" and after.string == ">" and after.start == tok.end)):
            # IEC's comparisons: a lone = is never Python here (an action's target is split
            # off before; `f(x=1)` stays a keyword argument, refused), <> is two tokens
            start = starts[tok.start[0] - 1] + tok.start[1]
            end = start + (1 if word == "=" else 2)
            edits.append((start, end, "==" if word == "=" else "!="))
        if (tok.type == tokenize.NAME and previous != "." and word.upper() in IEC_WORDS
                and word in (word.upper(), word.capitalize())):
            upper = word.upper()
            used.add(upper)
            if upper == "XOR":
                return text, frozenset(used)
            start = starts[tok.start[0] - 1] + tok.start[1]
            end = starts[tok.end[0] - 1] + tok.end[1]
            edits.append((start, end, _TO_PYTHON[upper]))
        if tok.type not in (tokenize.NL, tokenize.NEWLINE, tokenize.COMMENT):
            previous = word
    for start, end, new in reversed(edits):
        text = text[:start] + new + text[end:]
    return text, frozenset(used)


def unrewrite(text: str) -> str:
    """ast.unparse's text of a rewritten tree back in IEC words, so that compiling it again
    (a subnet's expression after parameter substitution, a part of a guard core/whyguard.py
    shows) gives the same meaning. A compiled expression has `~` and `@` only as NOT and MOD."""
    tokens = _tokens(text)
    if tokens is None:
        return text
    starts = _offsets(text)
    edits = [(starts[t.start[0] - 1] + t.start[1], starts[t.end[0] - 1] + t.end[1],
              {"~": "NOT ", "@": "MOD"}[t.string])  # unparse spaces binary operators
             for t in tokens if t.type == tokenize.OP and t.string in ("~", "@")]
    for start, end, new in reversed(edits):
        text = text[:start] + new + text[end:]
    return text
