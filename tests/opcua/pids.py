"""Which process of a running `softplc run` to signal: the scan process (from the HTTP API's
status) and the process listening on a port (the OPC UA service process: its socket's owner,
from /proc, Linux)."""

from __future__ import annotations

import contextlib
import json
import os
import urllib.request
from pathlib import Path


def api_status(api_port: int, token: str) -> dict[str, object]:
    request = urllib.request.Request(f"http://127.0.0.1:{api_port}/api/v1/status",
                                     headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(request, timeout=5) as reply:
        document: dict[str, object] = json.load(reply)
    return document


def listener_pid(port: int) -> int:
    """The pid holding the TCP socket that listens on 127.0.0.1:`port` (state 0A)."""
    inodes = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[3] == "0A" and int(fields[1].split(":")[1], 16) == port:
            inodes.add(f"socket:[{fields[9]}]")
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError):
            for fd in (entry / "fd").iterdir():
                with contextlib.suppress(OSError):
                    if os.readlink(fd) in inodes:
                        return int(entry.name)
    raise LookupError(f"no process of this user listens on port {port}")
