"""Refusing a request: the {"error", "problems"} answer and the checks of request parts that
every route shares (a boolean flag, a JSON body, an idempotency key).

Owns: ApiProblem (a 4xx/5xx answer with its located problems, never a traceback), the
small parsers that raise it, and the bounds of a JSON body (size, nesting depth, number
length), checked by a linear scan before the parser sees the body.
Does not know: routes, the channel, the scan.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from typing import Any, Final

from aiohttp import web

from softplc.core.errors import SoftplcError

_KEY: Final = re.compile(r"[\x21-\x7e]{1,64}")
_TRUE: Final = frozenset({"1", "true", "yes", "on"})
_FALSE: Final = frozenset({"0", "false", "no", "off", ""})
# A JSON body here is a value write ({"value": n}): far below these. The depth and number
# bounds keep the parser out of its recursion limit (RecursionError at ~1,000 levels) and
# Python's int conversion limit (ValueError beyond 4,300 digits).
MAX_JSON_BYTES: Final = 4096  # scanned on the event loop: under 1 ms at worst
MAX_JSON_DEPTH: Final = 32
MAX_NUMBER_CHARS: Final = 40
_TOKEN: Final = re.compile(rb'[\[\]{}"]|-?[0-9][-+0-9.eE]*')
_STRING_REST: Final = re.compile(rb'(?:[^"\\]++|\\.)*+"', re.DOTALL)


class ApiProblem(SoftplcError):
    """A request the service refuses: rendered as {"error", "problems"} with `status`."""

    def __init__(self, status: int, error: str, problems: Iterable[str] = (),
                 headers: Mapping[str, str] | None = None, **extra: Any) -> None:
        super().__init__(error)
        self.status = status
        self.error = error
        self.problems = list(problems)
        self.headers = dict(headers or {})
        self.extra = extra

    def response(self) -> web.Response:
        body = {"error": self.error, "problems": self.problems, **self.extra}
        return web.json_response(body, status=self.status, headers=self.headers)


def flag(value: str | None, what: str) -> bool:
    """A query or header flag: true/false, 1/0, yes/no, on/off; absent is false."""
    text = (value or "").strip().lower()
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise ApiProblem(400, f"{what} must be true or false, not {value!r}")


async def json_body(request: web.Request) -> Any:
    """The request's JSON body, refused with one located line when malformed or too big."""
    if (request.content_length or 0) > MAX_JSON_BYTES:
        raise ApiProblem(413, f"JSON body of {request.content_length} bytes: at most "
                              f"{MAX_JSON_BYTES}")
    data = await request.read()
    if len(data) > MAX_JSON_BYTES:
        raise ApiProblem(413, f"JSON body of {len(data)} bytes: at most {MAX_JSON_BYTES}")
    check_json_shape(data)
    try:
        return json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ApiProblem(400, f"the body must be JSON like {{\"value\": 1}}: {exc}") from None
    except (RecursionError, ValueError) as exc:  # the scan should have caught it: never a 500
        raise ApiProblem(400, f"the body is not usable JSON: {str(exc)[:120]}") from None


def check_json_shape(data: bytes) -> None:
    """Refuse nesting deeper than MAX_JSON_DEPTH and numbers longer than MAX_NUMBER_CHARS,
    naming where; in one pass, linear in the body (strings are skipped whole). Syntax errors
    are left to the parser, which locates them itself."""
    depth, pos = 0, 0
    while (token := _TOKEN.search(data, pos)) is not None:
        text, pos = token.group(), token.end()
        if text == b'"':
            rest = _STRING_REST.match(data, pos)
            if rest is None:
                return  # an unterminated string: the parser says so
            pos = rest.end()
        elif text in (b"[", b"{"):
            depth += 1
            if depth > MAX_JSON_DEPTH:
                raise ApiProblem(400, f"the body nests deeper than {MAX_JSON_DEPTH} levels at "
                                      f"{_where(data, token.start())}")
        elif text in (b"]", b"}"):
            depth -= 1
        elif len(text) > MAX_NUMBER_CHARS:
            raise ApiProblem(400, f"the number at {_where(data, token.start())} has "
                                  f"{len(text)} characters: at most {MAX_NUMBER_CHARS}")


def _where(data: bytes, offset: int) -> str:
    line, column = data.count(b"\n", 0, offset) + 1, offset - data.rfind(b"\n", 0, offset)
    return f"line {line}, column {column}"


def idempotency_key(request: web.Request) -> str | None:
    key = request.headers.get("Idempotency-Key")
    if key is not None and not _KEY.fullmatch(key):
        raise ApiProblem(400, "Idempotency-Key must be 1 to 64 printable ASCII characters")
    return key
