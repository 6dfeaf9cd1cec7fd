"""A client of the HTTP management service, standard library only: an http URL over plainhttp.py
(a socket, issue 40: urllib.request costs a start ~19 ms), https and the event stream urllib.

Owns: ApiClient (one method per endpoint), ApiError (a 4xx/5xx answer with its problems),
ApiUnreachable (nothing answers at the URL), the event-stream reader.
Does not know: argparse or exit codes (clicmds.py), the server's internals.

Proxies from the environment and redirects are not followed: the token must go to the
PLC named by the URL and nowhere else. Over https the server is verified against a CA file:
`ca`, else $SOFTPLC_API_CA, else the certificate of the PLC's state directory (given, or this
account's server at a loopback URL), else the system's CAs (security/tls.py, the pin rule).
"""

from __future__ import annotations

import json
import os
import re
import time
import urllib.parse
from pathlib import Path

from softplc.api import plainhttp
from softplc.core.errors import SoftplcError
from softplc.security import auth

TYPE_CHECKING = False  # typing costs a client command's start (issue 40); TLS: https only
if TYPE_CHECKING:
    from collections.abc import Iterator, Sequence
    from typing import Any, Final

DEFAULT_URL: Final = "http://127.0.0.1:8080"
URL_ENV: Final = "SOFTPLC_API"  # every client command's --api default (docs/api.md)
API: Final = "/api/v1"
_SILENCE_S: Final = 30.0  # two server heartbeats
DOWNLOAD_TIMEOUT_S: Final = 65.0  # the server waits up to 60 s for a big compile
# A command the service did not send because the PLC was not publishing is asked again for
# this long: a scan process starved for a moment on a busy host (stale after 200 ms) gets the
# command; a frozen or dead one is still reported within about a second.
NOT_SENT_WINDOW_S: Final = 1.0
NOT_SENT_RETRY_S: Final = 0.1
CA_ENV: Final = "SOFTPLC_API_CA"
SIGNATURE_HEADER: Final = "X-Softplc-Signature"  # api/signed.py reads it


def default_url() -> str:
    """The API a client command talks to without --api: $SOFTPLC_API, else DEFAULT_URL."""
    return os.environ.get(URL_ENV) or DEFAULT_URL


class ApiError(SoftplcError):
    """The service answered with an error status: `problems` lists every problem line of a
    refused program (FILE:LINE: path: message)."""

    def __init__(self, status: int, message: str, problems: Sequence[str] = (),
                 not_sent: bool = False) -> None:
        self.status = status
        self.message = message
        self.problems = tuple(problems)
        self.not_sent = not_sent  # a command the service did not send (the PLC was stale)
        super().__init__(f"HTTP {status}: {message}")


class ApiUnreachable(SoftplcError, ConnectionError):
    """Nothing answers at the API URL (refused, unresolvable, timed out, connection lost)."""


class ApiClient:
    """One softplc's API. `token` (a user's API key, or the owner's) falls back to
    $SOFTPLC_API_TOKEN, then to the api_token file of `state_dir` (when the client runs on
    the PLC's machine), then, for a loopback URL, to the api_token of the state directory
    that this account's server there uses (`local=False`: not that one). `user` and
    `password` send HTTP Basic instead."""

    def __init__(self, url: str = DEFAULT_URL, token: str | None = None,
                 timeout_s: float = 10.0, *, state_dir: Path | str | None = None,
                 user: str | None = None, password: str | None = None,
                 local: bool = True, ca: Path | str | None = None) -> None:
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ValueError(f"API URL must look like {DEFAULT_URL}, not {url!r}")
        self.url = url.rstrip("/")
        self.timeout_s = timeout_s
        if user is not None:
            import base64  # HTTP Basic only
            pair = base64.b64encode(f"{user}:{password or ''}".encode()).decode("ascii")
            self._authorization: str | None = f"Basic {pair}"
            self._find: tuple[str | None, Path | str | None, str | None] | None = None
        else:
            # Found again before a request while nothing is found: a client made before its
            # server started (which registers its owner's key) still authenticates.
            self._find = (token, state_dir, url if local else None)
            self._authorization = None
            self._credentials()
        self.ca: Path | None = None  # what an https server is verified against (None: system)
        self._plain = parts.scheme == "http"
        self._opener: Any = None  # urllib's, made at the first https or event-stream request
        if not self._plain:
            from softplc.security import tls
            self.ca = server_ca(ca, state_dir, url if local else None)
            self._opener = plainhttp.urllib_opener(tls.client_context(self.ca))

    def _credentials(self) -> str | None:
        if self._authorization is None and self._find is not None:
            found = auth.client_token(*self._find)
            self._authorization = f"Bearer {found}" if found else None
        return self._authorization

    def __repr__(self) -> str:
        return f"ApiClient({self.url!r}, token={'set' if self._authorization else 'none'})"

    # -- program handling -------------------------------------------------------------------

    def download(self, path_or_text: str | Path, online: bool = False,
                 name: str | None = None, replace: bool = False) -> dict[str, Any]:
        """Download a program file (a Path, or a string without a newline) or YAML text.
        `name` (default: the file's name) is what problem messages call the program."""
        if isinstance(path_or_text, str) and "\n" in path_or_text:
            return self.download_text(path_or_text, online, name, replace)
        path = Path(path_or_text)
        return self.download_text(path.read_text(encoding="utf-8"), online, name or path.name,
                                  replace)

    def download_text(self, text: str, online: bool = False, name: str | None = None,
                      replace: bool = False, dry_run: bool = False,
                      signature: str | None = None, allow_older: bool = False
                      ) -> dict[str, Any]:
        """`signature`: the line `softplc sign` made of exactly `text` (UTF-8);
        `allow_older`: take a signed version older than the running one (a rollback)."""
        query = _download_query(online, replace, dry_run, allow_older)
        if name:  # the server takes plain file names only
            query["name"] = re.sub(r"[^A-Za-z0-9._-]", "_", name)[:128]
        return self._json("POST", "/program", text.encode(), "application/yaml", query,
                          max(self.timeout_s, DOWNLOAD_TIMEOUT_S), _signed(signature))

    def download_bundle(self, blob: bytes, online: bool = False, replace: bool = False,
                        dry_run: bool = False, signature: str | None = None,
                        allow_older: bool = False) -> dict[str, Any]:
        """Download a bundle (softplc/program/bundle.py); with `dry_run` the answer's `plan`
        says what it would do, and nothing is applied. `signature`: of exactly `blob`;
        `allow_older`: as download_text."""
        query = _download_query(online, replace, dry_run, allow_older)
        return self._json("POST", "/program", blob, "application/zip", query,
                          max(self.timeout_s, DOWNLOAD_TIMEOUT_S), _signed(signature))

    def upload(self) -> bytes:
        """The running program's bundle, byte for byte."""
        return self._read(self._open("GET", "/program", None, None, None,
                                     headers={"Accept": "application/zip"}))

    def command(self, command: str) -> dict[str, Any]:
        """start, stop, resume, reset or kill: {"ok", "message", "state"}."""
        return self._json("POST", f"/{command}")

    def start(self) -> dict[str, Any]:
        return self.command("start")

    def stop(self) -> dict[str, Any]:
        return self.command("stop")

    def resume(self) -> dict[str, Any]:
        return self.command("resume")

    def reset(self) -> dict[str, Any]:
        return self.command("reset")

    def kill(self) -> dict[str, Any]:
        return self.command("kill")

    # -- breakpoints and single scans (docs/debug.md) ---------------------------------------

    def breakpoints(self) -> dict[str, Any]:
        """{"breakpoints": [...], "paused": {...} or None, "steps_left", "scan_count"}."""
        return self._json("GET", "/breakpoints")

    def add_breakpoint(self, on: str, target: str, outputs: str = "hold") -> dict[str, Any]:
        """`on` fire or enabled with a transition's name, or when with a condition."""
        key = "condition" if on == "when" else "transition"
        body = json.dumps({"on": on, key: target, "outputs": outputs}).encode()
        return self._json("POST", "/breakpoints", body, "application/json")

    def remove_breakpoint(self, ident: int | str | None = None) -> dict[str, Any]:
        """One breakpoint (3 or "b3"), or every one when `ident` is None."""
        return self._json("DELETE", "/breakpoints" if ident is None
                          else f"/breakpoints/{_quote(str(ident))}")

    def step(self, scans: int = 1) -> dict[str, Any]:
        """While paused: exactly `scans` scans, then paused again."""
        return self._json("POST", "/step", query={"scans": str(scans)})

    def continue_(self) -> dict[str, Any]:
        """While paused: run on until a breakpoint hits."""
        return self.command("continue")

    def why(self, transition: str) -> dict[str, Any]:
        """Why `transition` fires or not in the next round: {"verdict", "reasons", ...}."""
        return self._json("GET", f"/why/{_quote(transition)}")

    # -- status, symbols, events ------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        return self._json("GET", "/status")

    def symbols(self) -> dict[str, Any]:
        symbols: dict[str, Any] = self._json("GET", "/symbols")["symbols"]
        return symbols

    def symbol(self, name: str) -> dict[str, Any]:
        """{"name", "address", "type", "direction", "value"}, with "unit" and "scale" when
        the value is in engineering units."""
        entry: dict[str, Any] = self._json("GET", f"/symbols/{_quote(name)}")
        return entry

    def read_symbol(self, name: str) -> bool | int | float | str:
        """The typed value (a real as a number; "NaN"/"Infinity" as text)."""
        value: bool | int | float | str = self.symbol(name)["value"]
        return value

    def write_symbol(self, name: str, value: bool | int | float) -> dict[str, Any]:
        """Journal a write, applied at the next scan start (202)."""
        body = json.dumps({"value": value}).encode()
        return self._json("PUT", f"/symbols/{_quote(name)}", body, "application/json")

    # -- forcing (docs/web.md) ----------------------------------------------------------------

    def forces(self) -> dict[str, int | float]:
        forced: dict[str, int | float] = self._json("GET", "/forces").get("forced") or {}
        return forced

    def force(self, name: str, value: bool | int | float) -> dict[str, Any]:
        """Force `name` to `value` from the next scan on, until released."""
        body = json.dumps({"value": value}).encode()
        return self._json("PUT", f"/forces/{_quote(name)}", body, "application/json")

    def unforce(self, name: str | None = None) -> dict[str, Any]:
        """Release one force, or every force when `name` is None."""
        return self._json("DELETE", "/forces" if name is None else f"/forces/{_quote(name)}")

    def whoami(self) -> dict[str, Any]:
        """{"user", "role", "via"}: who this client is to the service."""
        return self._json("GET", "/whoami")

    def audit(self, since: str | None = None, limit: int = 1000) -> dict[str, Any]:
        """The audit trail's newest records and the chain's verdict (admin)."""
        query = {"limit": str(limit), **({"since": since} if since else {})}
        return self._json("GET", "/audit", query=query)

    def openapi(self) -> dict[str, Any]:
        return self._json("GET", "/openapi.json")

    def events(self, names: Sequence[str] = (), last_id: int | None = None
               ) -> Iterator[dict[str, Any]]:
        """Yield PLC events as they happen ({seq, scan, t_ns, name}); the stream ends when
        the server stops. Silence longer than two heartbeats (30 s) raises ApiUnreachable."""
        query = {"names": ",".join(names)} if names else None
        headers = {"Last-Event-ID": str(last_id)} if last_id is not None else {}
        timeout_s = max(self.timeout_s, _SILENCE_S)
        with self._open("GET", "/events", None, None, query, headers, timeout_s,
                        stream=True) as response:
            kind, data, pending = "message", list[str](), b""
            # read1, not line iteration: http.client's readline waits for more chunks
            while chunk := self._read(response, 65536):
                *lines, pending = (pending + chunk).split(b"\n")
                for raw in lines:
                    line = raw.decode("utf-8").rstrip("\r")
                    if not line:
                        if data and kind == "message":  # `event: overflow` is no PLC event
                            yield json.loads("\n".join(data))
                        kind, data = "message", []
                    elif line.startswith("data:"):
                        data.append(line[5:].lstrip())
                    elif line.startswith("event:"):
                        kind = line[6:].strip()

    # -- transport --------------------------------------------------------------------------

    def _json(self, method: str, path: str, body: bytes | None = None,
              content_type: str | None = None, query: dict[str, str] | None = None,
              timeout_s: float | None = None,
              headers: dict[str, str] | None = None) -> dict[str, Any]:
        # A command refused because the PLC was not publishing (a starved or restarting scan
        # process) was never sent: asking again until the timeout cannot apply it twice.
        give_up = time.monotonic() + min(timeout_s or self.timeout_s, NOT_SENT_WINDOW_S)
        while True:
            try:
                response = self._open(method, path, body, content_type, query, headers,
                                      timeout_s)
                break
            except ApiError as exc:
                if not exc.not_sent or time.monotonic() + NOT_SENT_RETRY_S > give_up:
                    raise
                time.sleep(NOT_SENT_RETRY_S)
        status, raw = response.status, self._read(response)
        try:
            answer = json.loads(raw or b"{}")
        except ValueError:
            answer = None
        if not isinstance(answer, dict):
            raise ApiError(status, f"{method} {path}: the answer is not a JSON object")
        return answer

    def _read(self, response: Any, size: int = 0) -> bytes:
        """The whole answer (closed after it), or (`size`) what has come of a stream."""
        try:
            return bytes(response.read1(size) if size else response.read())
        except OSError as exc:
            what = "event stream" if size else "answer"
            raise ApiUnreachable(f"the {what} from {self.url} broke off: {exc}") from None
        finally:
            if not size:
                response.close()

    def _open(self, method: str, path: str, body: bytes | None, content_type: str | None,
              query: dict[str, str] | None, headers: dict[str, str] | None = None,
              timeout_s: float | None = None, stream: bool = False) -> Any:
        path += "?" + urllib.parse.urlencode(query) if query else ""
        sent = {"Accept": "application/json", **(headers or {})}
        if content_type:
            sent["Content-Type"] = content_type
        if (credentials := self._credentials()) is not None:
            sent["Authorization"] = credentials
        timeout_s = timeout_s or self.timeout_s
        try:
            if self._plain and not stream:
                answer = plainhttp.request(self.url + API + path, method, sent, body, timeout_s)
            else:
                self._opener = self._opener or plainhttp.urllib_opener(None)
                answer = plainhttp.urllib_open(self._opener, self.url + API + path, method,
                                               sent, body, timeout_s)
        except OSError as exc:  # urllib's URLError too
            reason = getattr(exc, "reason", exc)
            raise ApiUnreachable(
                f"cannot reach the softplc API at {self.url}: {reason}. Is `softplc run` "
                f"serving its API there (--api HOST:PORT)?") from None
        if 200 <= answer.status < 300:
            return answer
        raise _api_error(answer)


def server_ca(ca: Path | str | None, state_dir: Path | str | None,
              url: str | None) -> Path | None:
    """The CA file to verify an https server against: `ca`, $SOFTPLC_API_CA, the certificate
    the PLC of `state_dir` (or of this account's server at a loopback `url`) serves with;
    None: the system's CAs."""
    if ca or (ca := os.environ.get(CA_ENV, "").strip()):
        return Path(ca)
    if state_dir is None and url is not None:
        state_dir = auth.indexed_state_dir(url)
    if state_dir is None:
        return None
    from softplc.api import secopts
    from softplc.security import tls
    given = secopts.load(Path(state_dir)).tls.cert
    cert = Path(given) if given else tls.generated_paths(Path(state_dir))[0]
    return cert if cert.is_file() else None


def _download_query(online: bool, replace: bool, dry_run: bool,
                    allow_older: bool) -> dict[str, str]:
    query = {"online": "true" if online else "false"}
    query.update({flag: "true" for flag, given in (
        ("replace", replace), ("dry_run", dry_run), ("allow_older", allow_older)) if given})
    return query


def _signed(signature: str | None) -> dict[str, str] | None:
    return {SIGNATURE_HEADER: signature.strip()} if signature else None


def _quote(name: str) -> str:
    return urllib.parse.quote(name, safe="")


def _api_error(answer: Any) -> ApiError:
    """A non-2xx answer (a 3xx too: no redirect is followed) as an ApiError."""
    code, reason = answer.status, str(answer.reason)
    try:
        raw = answer.read()
    except OSError:
        raw = b""
    finally:
        answer.close()
    try:
        body = json.loads(raw)
    except ValueError:
        body = None
    problems: list[str] = []
    if isinstance(body, dict) and "error" in body:
        text = str(body["error"])
        problems = [str(p) for p in body.get("problems") or []]
    else:
        text = raw.decode("utf-8", "replace").strip()[:200] or reason
    if code == 401:
        text += (f" (give --token with an API key, set ${auth.TOKEN_ENV}, --user, or "
                 "--state-dir of the server)")
    not_sent = code == 503 and isinstance(body, dict) and body.get("stale") is True
    return ApiError(code, text, problems, not_sent)
