"""Refusing a request: the {"error", "problems"} answer and the checks of request parts that
every route shares (a boolean flag, a JSON body, an idempotency key).

Owns: ApiProblem (a 4xx/5xx answer with its located problems, never a traceback) and the
small parsers that raise it.
Does not know: routes, the channel, the scan.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping
from typing import Any, Final

from aiohttp import web

_KEY: Final = re.compile(r"[\x21-\x7e]{1,64}")
_TRUE: Final = frozenset({"1", "true", "yes", "on"})
_FALSE: Final = frozenset({"0", "false", "no", "off", ""})


class ApiProblem(Exception):
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
    try:
        return json.loads(await request.read())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ApiProblem(400, f"the body must be JSON like {{\"value\": 1}}: {exc}") from None


def idempotency_key(request: web.Request) -> str | None:
    key = request.headers.get("Idempotency-Key")
    if key is not None and not _KEY.fullmatch(key):
        raise ApiProblem(400, "Idempotency-Key must be 1 to 64 printable ASCII characters")
    return key
