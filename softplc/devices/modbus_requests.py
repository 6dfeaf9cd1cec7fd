"""The Modbus requests a remote-I/O driver sends: one block read or written, one holding
register written (heartbeat, watchdog setup), and every output block written on a synchronous
client (go_safe's and close's fallback when the I/O thread cannot).

Owns: Client and SyncClient (the requests a transport's client must answer: pymodbus's own
clients, or one unit of a serial line), request and reply checking (a Modbus exception or a
short reply is a RemoteError), pymodbus's log level.
Does not know: threads, sequence numbers, the scan, which wire (TCP or serial) carries them.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Sequence
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU

from softplc.core.image import BoolArray, WordArray
from softplc.devices.driver import DeviceError
from softplc.devices.modbus_plan import Block, Table

ERRORS = (TimeoutError, ModbusException, DeviceError, OSError)  # what a request may raise


class RemoteError(DeviceError):
    """The remote device answered a request with a Modbus exception or a short reply."""


class Client(Protocol):
    """The I/O thread's client: pymodbus's AsyncModbusTcpClient has this shape."""

    @property
    def connected(self) -> bool: ...
    async def connect(self) -> bool: ...
    def close(self) -> None: ...
    def read_coils(self, address: int, *, count: int, device_id: int
                   ) -> Awaitable[ModbusPDU]: ...
    def read_discrete_inputs(self, address: int, *, count: int, device_id: int
                             ) -> Awaitable[ModbusPDU]: ...
    def read_holding_registers(self, address: int, *, count: int, device_id: int
                               ) -> Awaitable[ModbusPDU]: ...
    def read_input_registers(self, address: int, *, count: int, device_id: int
                             ) -> Awaitable[ModbusPDU]: ...
    def write_coils(self, address: int, values: list[bool], *, device_id: int
                    ) -> Awaitable[ModbusPDU]: ...
    def write_registers(self, address: int, values: list[int], *, device_id: int
                        ) -> Awaitable[ModbusPDU]: ...
    def write_register(self, address: int, value: int, *, device_id: int
                       ) -> Awaitable[ModbusPDU]: ...


class SyncClient(Protocol):
    """A connected synchronous client, for the direct write (pymodbus's sync clients)."""

    def write_coils(self, address: int, values: list[bool], *, device_id: int
                    ) -> ModbusPDU: ...
    def write_registers(self, address: int, values: list[int], *, device_id: int
                        ) -> ModbusPDU: ...


async def read_block(client: Client, block: Block, unit: int
                     ) -> BoolArray | WordArray:
    request = {
        Table.COIL: client.read_coils,
        Table.DI: client.read_discrete_inputs,
        Table.HR: client.read_holding_registers,
        Table.IR: client.read_input_registers,
    }[block.table]
    reply = checked(await request(block.start, count=block.count, device_id=unit), block)
    values = reply.bits if block.table.is_bit else reply.registers
    if len(values) < block.count:
        raise RemoteError(f"{block}: short reply ({len(values)} values)")
    dtype: npt.DTypeLike = np.bool_ if block.table.is_bit else np.uint16
    return np.asarray(values[: block.count], dtype=dtype)


async def write_block(client: Client, block: Block, values: list[Any],
                      unit: int) -> None:
    if block.table is Table.COIL:
        reply = await client.write_coils(block.start, values, device_id=unit)
    else:
        reply = await client.write_registers(block.start, values, device_id=unit)
    checked(reply, block)


async def write_word(client: Client, register: int, value: int,
                     unit: int) -> None:
    """One holding register (FC 6)."""
    reply = await client.write_register(register, value, device_id=unit)
    checked(reply, Block(Table.HR, register, (0,)))


def write_all(client: SyncClient, unit: int, blocks: Sequence[Block],
              outputs: Sequence[list[Any]]) -> None:
    """`outputs` (one value list per block), each acknowledged or raising one of ERRORS."""
    for block, values in zip(blocks, outputs, strict=True):
        if block.table is Table.COIL:
            reply = client.write_coils(block.start, values, device_id=unit)
        else:
            reply = client.write_registers(block.start, values, device_id=unit)
        checked(reply, block)


def checked(reply: ModbusPDU, block: Block) -> ModbusPDU:
    if reply.isError():
        raise RemoteError(f"{block}: Modbus exception code {reply.exception_code}")
    return reply


def quiet_pymodbus() -> None:
    """pymodbus logs warnings and errors with frame dumps on every failed (re)connect and
    timeout; our own logger reports state changes once. An explicitly set level is kept."""
    logger = logging.getLogger("pymodbus")
    if logger.level == logging.NOTSET:
        logger.setLevel(logging.CRITICAL)
