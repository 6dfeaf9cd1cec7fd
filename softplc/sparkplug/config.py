"""`softplc run --sparkplug URL`: the edge node's configuration.

Owns: SparkplugConfig (a frozen value: it crosses into the Sparkplug process by pickling)
and parsing `mqtt://[USER[:PASSWORD]@]HOST:PORT/GROUP/EDGE_NODE` (or `mqtts://`) with a
clear error naming what is wrong and what is expected.
Does not know: the run options (options.py), MQTT sessions, payloads, symbols.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final
from urllib.parse import unquote, urlsplit

from softplc.security.roles import Role

if TYPE_CHECKING:  # numpy: not for `softplc run --help`
    from softplc.core.image import ImageSizes

_FORBIDDEN: Final = frozenset("+/#")  # MQTT wildcards and the level separator (spec 4.1)


@dataclass(frozen=True, slots=True)
class SparkplugConfig:
    host: str
    port: int
    group: str
    node: str
    tls: bool = False
    user: str | None = None
    password: str | None = None
    ca_file: str | None = None
    role: Role = Role.VIEWER  # what a host's NCMD/DCMD may do: viewer writes nothing
    commands: bool = False  # program commands (start/stop/resume/reset) by NCMD
    primary_host: str | None = None  # births wait for this host's STATE online
    interval_s: float = 0.1  # NDATA at most this often (report by exception)
    deadband: float = 0.0  # a real (or scaled) metric changes by more than this to be sent
    state_dir: str = "state"
    keepalive_s: int = 10
    sizes: ImageSizes | None = None  # None: the runtime's default sizes
    # The process entry the supervisor starts (options.py sets it: sparkplug/process.py);
    # runtime never imports this room.
    main: Callable[..., None] | None = None

    @property
    def broker(self) -> tuple[str, int]:
        return self.host, self.port

    def __repr__(self) -> str:  # never the password, in a log or a traceback
        scheme = "mqtts" if self.tls else "mqtt"
        return f"SparkplugConfig({scheme}://{self.host}:{self.port}/{self.group}/{self.node})"


def parse_url(url: str) -> SparkplugConfig:
    """The broker and ids of `url`; ValueError saying what is wrong and what is expected."""
    expected = "expected mqtt://[USER[:PASSWORD]@]HOST:PORT/GROUP/EDGE_NODE (or mqtts://)"
    parts = urlsplit(url)
    if parts.scheme not in ("mqtt", "mqtts"):
        raise ValueError(f"{url!r}: the scheme must be mqtt or mqtts; {expected}")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"{url!r}: the port is not a number 1..65535; {expected}") from None
    if not parts.hostname or port is None or port == 0:
        raise ValueError(f"{url!r}: HOST:PORT is missing; {expected}")
    ids = [unquote(p) for p in parts.path.split("/")[1:]]
    if len(ids) != 2 or not all(ids):
        raise ValueError(f"{url!r}: the path must be /GROUP/EDGE_NODE; {expected}")
    for what, text in zip(("group", "edge node"), ids, strict=True):
        if _FORBIDDEN & set(text):
            raise ValueError(f"{url!r}: the {what} id {text!r} holds + / or # (Sparkplug "
                             "4.1: not in ids)")
    if parts.query or parts.fragment:
        raise ValueError(f"{url!r}: no query or fragment is read; {expected}")
    return SparkplugConfig(parts.hostname, port, ids[0], ids[1], tls=parts.scheme == "mqtts",
                           user=unquote(parts.username) if parts.username else None,
                           password=unquote(parts.password) if parts.password else None)


