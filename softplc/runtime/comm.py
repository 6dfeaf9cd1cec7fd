"""The communication process: Modbus TCP slave and HTTP API on one asyncio loop.

Owns: starting both services against the published snapshot (shared memory) and the command
channel, and stopping them. A crash here never stops the scan: it is another process.
Does not know: the scan loop's internals.
"""

from __future__ import annotations

import asyncio
import logging
import os
import signal
from dataclasses import dataclass
from multiprocessing.synchronize import Event
from pathlib import Path

from softplc.core.image import ImageSizes
from softplc.core.snapshot import HmiWrite
from softplc.runtime.board import StatusBoard
from softplc.runtime.channel import Channel
from softplc.runtime.shm import SnapshotReader

log = logging.getLogger("softplc.comm")


@dataclass(frozen=True, slots=True)
class CommConfig:
    modbus: tuple[str, int] | None = ("127.0.0.1", 5020)
    api: tuple[str, int] | None = ("127.0.0.1", 8080)
    state_dir: str = "state"
    sizes: ImageSizes = ImageSizes()
    modbus_read_only: bool = False


async def _serve(config: CommConfig, channel: Channel, shm_name: str, board_name: str,
                 ready: Event, stop: Event) -> None:
    reader = SnapshotReader.attach(shm_name, config.sizes)
    board = StatusBoard.attach(board_name)
    services = []
    if config.modbus is not None:
        from softplc.hmi.server import ModbusSlave

        def sink(write: HmiWrite) -> None:
            channel.send_hmi_write(write)

        host, port = config.modbus
        slave = ModbusSlave(reader, sink, sizes=config.sizes, host=host, port=port,
                            read_only=config.modbus_read_only)
        await slave.start()
        services.append(slave)
    if config.api is not None:
        from softplc.api.server import ApiServer

        host, port = config.api
        api = ApiServer(channel, reader, board, host=host, port=port,
                        state_dir=Path(config.state_dir))
        await api.start()
        services.append(api)
    ready.set()
    parent = os.getppid()
    try:
        while not stop.is_set() and os.getppid() == parent:
            await asyncio.sleep(0.1)
    finally:
        for service in reversed(services):
            await service.stop()
        reader.close()
        board.close()


def comm_process_main(config: CommConfig, channel: Channel, shm_name: str, board_name: str,
                      ready: Event, stop: Event) -> None:
    from softplc.runtime.supervisor import die_with_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    die_with_parent()
    asyncio.run(_serve(config, channel, shm_name, board_name, ready, stop))
