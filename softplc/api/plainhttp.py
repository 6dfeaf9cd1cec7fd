"""Plain HTTP/1.1 over `socket` for the CLI's client commands (issue 40): one request per
connection (Connection: close), the answer's body read by its Content-Length, chunked, or to
the end of the connection. urllib.request costs a command's start ~19 ms of imports (http.client,
email, ssl); this costs none beyond `socket`.

Owns: request (one exchange), Response (its status, headers, body), ProtocolError, and
urllib_opener: urllib's opener for what this does not do (https, the event stream's reads as
they come), imported only when one is made.
Does not know: the API's paths, JSON or errors (client.py).

Every failure is an OSError, as urllib's are: nothing answers (refused, unresolvable, timed
out), the connection closed before an answer, an answer that is not HTTP, or a body cut short.
"""

from __future__ import annotations

import socket
import urllib.parse

from softplc.core.errors import SoftplcError

TYPE_CHECKING = False  # typing costs a client command's start (issue 40)
if TYPE_CHECKING:
    from collections.abc import Mapping
    from typing import Any, BinaryIO, Final

_MAX_LINE: Final = 65536  # a status, header or chunk-size line longer than this is refused
_MAX_HEADERS: Final = 100


class ProtocolError(SoftplcError, ConnectionError):
    """The peer's answer is not HTTP/1.x, or it broke off inside the status line, a header or
    the body."""


class Response:
    """An answer whose status line and headers are read; the body is read by `read`."""

    def __init__(self, sock: socket.socket, stream: BinaryIO, status: int, reason: str,
                 headers: dict[str, str]) -> None:
        self._sock = sock
        self._stream = stream
        self.status = status
        self.reason = reason
        self.headers = headers  # names in lower case; a repeated header: its last value

    def read(self) -> bytes:
        """The whole body (the connection is closed after it)."""
        try:
            if "chunked" in self.headers.get("transfer-encoding", "").lower():
                return self._chunked()
            length = self.headers.get("content-length")
            if length is not None:
                if not length.strip().isdigit():
                    raise ProtocolError(f"bad Content-Length {length!r}")
                return self._exactly(int(length))
            return self._stream.read()  # no length: up to the end of the connection
        finally:
            self.close()

    def _exactly(self, size: int) -> bytes:
        data = self._stream.read(size)
        if len(data) < size:
            raise ProtocolError(f"the body ended after {len(data)} of {size} bytes")
        return data

    def _chunked(self) -> bytes:
        parts: list[bytes] = []
        while True:
            line = _line(self._stream)
            size_text = line.split(b";", 1)[0].strip()
            try:
                size = int(size_text, 16)
            except ValueError:
                raise ProtocolError(f"bad chunk size {size_text[:40]!r}") from None
            if size == 0:
                break
            parts.append(self._exactly(size))
            _line(self._stream)  # the CRLF after the chunk
        while _line(self._stream) not in (b"\r\n", b"\n"):  # trailers, then the blank line
            pass
        return b"".join(parts)

    def close(self) -> None:
        self._stream.close()
        self._sock.close()

    def __enter__(self) -> Response:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def request(url: str, method: str, headers: Mapping[str, str], body: bytes | None,
            timeout_s: float) -> Response:
    """Send one request to an http URL (its host a name, an IPv4 or a bracketed IPv6 address:
    http://[::1]:8080/...). The timeout bounds the connect and each read or write. A port that
    is no number: ValueError, as urllib."""
    parts = urllib.parse.urlsplit(url)
    host, port = parts.hostname or "", parts.port or 80
    target = (parts.path or "/") + (f"?{parts.query}" if parts.query else "")
    # An ASCII name as bytes: getaddrinfo encodes a str by the idna codec (~1.3 ms of imports)
    address = (host.encode("ascii") if host.isascii() else host, port)
    sock = socket.create_connection(address, timeout=timeout_s)  # type: ignore[arg-type]
    stream: BinaryIO | None = None
    try:
        lines = [f"{method} {target} HTTP/1.1", f"Host: {parts.netloc.rpartition('@')[2]}",
                 *(f"{k}: {v}" for k, v in headers.items()),
                 "Connection: close", f"Content-Length: {len(body or b'')}", "", ""]
        sock.sendall("\r\n".join(lines).encode("latin-1") + (body or b""))
        stream = sock.makefile("rb")
        status, reason = _status_line(stream)
        while 100 <= status < 200:  # an interim answer (100 Continue): its headers, then on
            _headers(stream)
            status, reason = _status_line(stream)
        return Response(sock, stream, status, reason, _headers(stream))
    except BaseException:
        if stream is not None:
            stream.close()
        sock.close()
        raise


def _line(stream: BinaryIO) -> bytes:
    line = stream.readline(_MAX_LINE + 1)
    if len(line) > _MAX_LINE:
        raise ProtocolError("a line of the answer is too long")
    if not line.endswith(b"\n"):
        raise ProtocolError("the answer broke off")
    return line


def _status_line(stream: BinaryIO) -> tuple[int, str]:
    first = stream.readline(_MAX_LINE + 1)
    if not first:  # the words of http.client (and so of urllib) for this case
        raise ProtocolError("Remote end closed connection without response")
    version, _, rest = first.decode("latin-1").rstrip("\r\n").partition(" ")
    code, _, reason = rest.partition(" ")
    if not version.startswith("HTTP/1.") or len(code) != 3 or not code.isdigit():
        raise ProtocolError(f"not an HTTP answer: {first[:60]!r}")
    return int(code), reason.strip()


def _headers(stream: BinaryIO) -> dict[str, str]:
    found: dict[str, str] = {}
    for _ in range(_MAX_HEADERS):
        line = _line(stream)
        if line in (b"\r\n", b"\n"):
            return found
        name, colon, value = line.decode("latin-1").partition(":")
        if not colon:
            raise ProtocolError(f"bad header line {line[:60]!r}")
        found[name.strip().lower()] = value.strip()
    raise ProtocolError(f"more than {_MAX_HEADERS} headers")


def urllib_opener(context: Any) -> Any:
    """urllib's opener, with `context` (a TLS client context) for https; no proxy from the
    environment and no redirect: the Authorization header goes to the URL's host only."""
    import urllib.request

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args: Any, **kwargs: Any) -> None:
            return None  # a 3xx becomes an HTTPError

    handlers: list[urllib.request.BaseHandler] = [urllib.request.ProxyHandler({}), NoRedirect()]
    if context is not None:
        handlers.append(urllib.request.HTTPSHandler(context=context))
    return urllib.request.build_opener(*handlers)


def urllib_open(opener: Any, url: str, method: str, headers: Mapping[str, str],
                body: bytes | None, timeout_s: float) -> Any:
    """One request through `opener`: the answer, an error status's too (HTTPError, which has
    the same status, reason and read)."""
    import urllib.error
    import urllib.request

    try:
        return opener.open(urllib.request.Request(url, data=body, method=method,
                                                  headers=dict(headers)), timeout=timeout_s)
    except urllib.error.HTTPError as exc:
        return exc
