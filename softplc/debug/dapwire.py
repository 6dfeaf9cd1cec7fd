"""The Debug Adapter Protocol's framing: a message is `Content-Length: N` (and possibly other
headers), a blank line, then N bytes of UTF-8 JSON (the base protocol of the DAP
specification).

Owns: reading one message from a byte stream, encoding one.
Does not know: what the messages mean (debug/dap.py), sockets.
"""

from __future__ import annotations

import json
from typing import IO, Any, Final

from softplc.core.errors import SoftplcError

MAX_BODY: Final = 16 * 1024 * 1024  # a message no editor sends; a broken peer is cut off
MAX_HEADER: Final = 4096


class WireError(SoftplcError, ValueError):
    """The peer sent something that is not a DAP message."""


def encode(message: dict[str, Any]) -> bytes:
    body = json.dumps(message, separators=(",", ":")).encode("utf-8")
    return b"Content-Length: %d\r\n\r\n" % len(body) + body


def read_message(stream: IO[bytes]) -> dict[str, Any] | None:
    """The next message, or None at the end of the stream (before a header)."""
    length = None
    first = True
    while True:
        line = stream.readline(MAX_HEADER)
        if not line:
            if first:
                return None
            raise WireError("the stream ended inside a header")
        first = False
        text = line.decode("ascii", "replace").strip()
        if not text:
            break
        name, _, value = text.partition(":")
        if name.strip().lower() == "content-length":
            try:
                length = int(value.strip())
            except ValueError:
                raise WireError(f"bad Content-Length {value.strip()!r}") from None
    if length is None or not 0 <= length <= MAX_BODY:
        raise WireError(f"no usable Content-Length (got {length})")
    body = stream.read(length)
    if len(body) < length:
        raise WireError("the stream ended inside a message")
    try:
        message = json.loads(body)
    except ValueError as exc:
        raise WireError(f"the body is not JSON: {exc}") from None
    if not isinstance(message, dict):
        raise WireError("the body is not a JSON object")
    return message
