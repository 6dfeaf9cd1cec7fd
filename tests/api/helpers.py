"""A raw HTTP helper (http.client) for tests that need exact status codes and headers.

`call` sends what it is given, credentials included: without them a loopback service treats
it as a viewer. `owner=True` adds the owner's key, found as the owner's CLI finds it (the
index of this account's local servers, softplc/security/auth.py)."""

from __future__ import annotations

import http.client
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from softplc.api.commands import DOWNLOAD_DEADLINE_S, REPLY_GRACE_S
from softplc.security import auth

ROOT = Path(__file__).resolve().parents[2]
TRANSPORT = ROOT / "programs" / "transport.yaml"
DRILLING = ROOT / "programs" / "drilling.yaml"
BAD_PROGRAM = """program: broken
io_image: ../io_images/transport.yaml
places:
  a: {tokens: many}
  b: {tokens: -1}
transitions:
  t: {from: [nowhere], to: [a], when: "s1_i and"}
"""


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    raw: bytes

    @property
    def body(self) -> Any:
        return json.loads(self.raw)


# As long as the server may take to answer any request (a download's deadline and grace):
# a client that waits less tests its own patience on a loaded machine, not the server.
ANSWER_WITHIN_S = DOWNLOAD_DEADLINE_S + REPLY_GRACE_S + 5.0


def owner_headers(url: str) -> dict[str, str]:
    """The Authorization header of the owner of the local server at `url`."""
    token = auth.client_token(None, None, url)
    assert token, f"no owner's key found for {url}"
    return {"Authorization": f"Bearer {token}"}


def call(url: str, method: str, path: str, body: bytes | str | None = None,
         headers: dict[str, str] | None = None, timeout_s: float = 10.0, *,
         owner: bool = False) -> Answer:
    if owner:
        headers = {**owner_headers(url), **(headers or {})}
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname or "", parts.port, timeout=timeout_s)
    try:
        data = body.encode() if isinstance(body, str) else body
        conn.request(method, path, body=data, headers=headers or {})
        response = conn.getresponse()
        return Answer(response.status, dict(response.getheaders()), response.read())
    finally:
        conn.close()
