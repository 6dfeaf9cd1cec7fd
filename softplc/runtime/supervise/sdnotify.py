"""systemd's notification protocol (sd_notify), without a dependency.

Owns: READY=1 once both processes serve, WATCHDOG=1 while the supervisor's loop runs (when
the unit sets WatchdogSec), STATUS= lines, STOPPING=1. A no-op outside systemd (no
NOTIFY_SOCKET). Does not know: what is supervised.
"""

from __future__ import annotations

import contextlib
import os
import socket


class Notifier:
    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "")
        if address.startswith("@"):  # an abstract socket
            address = "\0" + address[1:]
        self._address = address or None
        usec = os.environ.get("WATCHDOG_USEC", "")
        # Ping at half the interval systemd allows, as sd_watchdog_enabled(3) advises.
        self.watchdog_s = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 else None
        self._last_ping = 0.0

    def send(self, message: str) -> None:
        if self._address is None:
            return
        with contextlib.suppress(OSError), socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
            s.connect(self._address)
            s.sendall(message.encode())

    def ping(self, now_s: float) -> None:
        """WATCHDOG=1 when due: the supervisor's loop is alive (it heals what died)."""
        if self.watchdog_s is not None and now_s - self._last_ping >= self.watchdog_s:
            self._last_ping = now_s
            self.send("WATCHDOG=1")
