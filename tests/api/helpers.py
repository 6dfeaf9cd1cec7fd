"""A raw HTTP helper (http.client) for tests that need exact status codes and headers."""

from __future__ import annotations

import http.client
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

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


def call(url: str, method: str, path: str, body: bytes | str | None = None,
         headers: dict[str, str] | None = None, timeout_s: float = 10.0) -> Answer:
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname or "", parts.port, timeout=timeout_s)
    try:
        data = body.encode() if isinstance(body, str) else body
        conn.request(method, path, body=data, headers=headers or {})
        response = conn.getresponse()
        return Answer(response.status, dict(response.getheaders()), response.read())
    finally:
        conn.close()
