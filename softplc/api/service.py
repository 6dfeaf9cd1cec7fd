"""What the HTTP routes need of the service that hands them requests.

Owns: the Protocols between the API's parts: CommandChannel and BoardSource (what the service
needs of the runtime's channel and status board) and ApiService (what the route modules
programs.py, symbols.py and web.py need of server.py's ApiServer), so that no route module
imports the server that imports it.
Does not know: aiohttp's application, the routes themselves.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from aiohttp import web

from softplc.api.commands import Record
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.snapshot import CommandReply, CommandRequest, HmiWrite, SnapshotSource


class CommandChannel(Protocol):
    """What the service needs of softplc.runtime.shared.channel.Channel (client side)."""

    def send_command(self, request: CommandRequest, timeout_s: float = ...,
                     on_late: Callable[[CommandReply], None] | None = ...) -> CommandReply: ...

    def send_hmi_write(self, write: HmiWrite) -> None: ...


class BoardSource(Protocol):
    """What the service needs of softplc.runtime.shared.board.StatusBoard."""

    def read(self) -> dict[str, Any]: ...


class ApiService(Protocol):
    """What a route module uses of the service (server.py's ApiServer)."""

    @property
    def state_dir(self) -> Path: ...
    @property
    def heartbeat_s(self) -> float: ...
    @property
    def channel(self) -> CommandChannel: ...
    @property
    def snapshots(self) -> SnapshotSource: ...

    async def board_document(self) -> dict[str, Any]: ...

    async def command(self, command: Command, text: str | None = None,
                      name: str | None = None, online: bool = False,
                      key: str | None = None, symbol: str | None = None,
                      value: int = 0, replace: bool = False, bundle: bytes | None = None,
                      dry_run: bool = False) -> CommandReply | Record: ...

    def answer(self, reply: CommandReply | Record) -> web.Response: ...

    def image(self) -> tuple[int, ProcessImage | None]: ...
