"""The Modbus requests a remote-I/O driver sends: one block read or written, one holding
register written (heartbeat, watchdog setup), and the outputs written on a fresh synchronous
connection within a deadline (go_safe's and close's fallback when the I/O thread cannot).

Owns: request and reply checking (a Modbus exception or a short reply is a RemoteError),
pymodbus's log level. Does not know: threads, sequence numbers, the scan.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt
from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException
from pymodbus.pdu import ModbusPDU

from softplc.core.image import BoolArray, WordArray
from softplc.devices.driver import DeviceError
from softplc.devices.modbus_params import ModbusParams
from softplc.devices.modbus_plan import Block, Table

ERRORS = (TimeoutError, ModbusException, DeviceError, OSError)  # what a request may raise


class RemoteError(DeviceError):
    """The remote device answered a request with a Modbus exception or a short reply."""


async def read_block(client: AsyncModbusTcpClient, block: Block, unit: int
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


async def write_block(client: AsyncModbusTcpClient, block: Block, values: list[Any],
                      unit: int) -> None:
    if block.table is Table.COIL:
        reply = await client.write_coils(block.start, values, device_id=unit)
    else:
        reply = await client.write_registers(block.start, values, device_id=unit)
    checked(reply, block)


async def write_word(client: AsyncModbusTcpClient, register: int, value: int,
                     unit: int) -> None:
    """One holding register (FC 6)."""
    reply = await client.write_register(register, value, device_id=unit)
    checked(reply, Block(Table.HR, register, (0,)))


def write_direct(params: ModbusParams, blocks: Sequence[Block],
                 outputs: Sequence[list[Any]], deadline: float) -> str:
    """`outputs` (one value list per block) on a fresh connection, each request bounded by
    what is left until `deadline` (time.monotonic()). "" when the device acknowledged every
    write, else why not."""
    left = deadline - time.monotonic()
    if left <= 0:
        return "no time left for a direct write"
    p = params
    client = ModbusTcpClient(p.host, port=p.port, timeout=min(p.timeout_s, left), retries=0,
                             reconnect_delay=0)
    try:
        if not client.connect():  # type: ignore[no-untyped-call]
            return f"cannot connect to {p.host}:{p.port}"
        for block, values in zip(blocks, outputs, strict=True):
            if block.table is Table.COIL:
                reply = client.write_coils(block.start, values, device_id=p.unit)
            else:
                reply = client.write_registers(block.start, values, device_id=p.unit)
            checked(reply, block)
    except ERRORS as exc:
        return f"direct write: {exc or type(exc).__name__}"
    finally:
        client.close()  # type: ignore[no-untyped-call]
    return ""


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
