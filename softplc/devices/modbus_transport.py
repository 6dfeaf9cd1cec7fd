"""The seam between a Modbus remote-I/O driver and its wire: what differs between Modbus TCP
and Modbus RTU (modbus_rtu.py) is here, everything else (plan, cycle, backoff, go_safe) is
shared by modbus_io.py and modbus_link.py.

Owns: Transport (the params, the I/O thread's client, the direct write of go_safe's fallback,
and what an open driver holds of a shared medium), Wire (a driver kind and its transport) and
the Modbus TCP ones.
Does not know: the process image, the scan, the I/O thread's cycle.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient

from softplc.core.symbols import DriverSpec
from softplc.devices.modbus_params import LinkParams, ModbusParams
from softplc.devices.modbus_plan import Block, IoPlan
from softplc.devices.modbus_requests import ERRORS, Client, write_all

OnLink = Callable[[bool], None]  # told True on every connect, False on a lost connection


class Transport(Protocol):
    """One driver's way to its device."""

    @property
    def params(self) -> LinkParams: ...

    @property
    def where(self) -> str:
        """The device in a few words, for messages ("10.0.0.20:502", "/dev/ttyUSB0 unit 2")."""
        ...

    @property
    def silence(self) -> str:
        """A request that got no reply within timeout_s, in the PLC's words ("unit 1 on
        /dev/ttyUSB0 did not answer within 0.5 s"), for the fault reason and problem()."""
        ...

    def client(self, on_link: OnLink) -> Client:
        """A new client for the I/O thread (made in that thread, on its loop)."""
        ...

    def attach(self) -> None:
        """The driver opens: claim what the device shares with others. DriverConfigError
        when another open driver holds it in a way this one cannot share."""
        ...

    def detach(self) -> None:
        """The driver has closed (its I/O thread ended): give back what attach() claimed."""
        ...

    def write_direct(self, blocks: Sequence[Block], outputs: Sequence[list[Any]],
                     deadline: float) -> str:
        """Write `outputs` without the I/O thread (it may be wedged), every request bounded
        by what is left until `deadline` (time.monotonic()). "" when the device acknowledged
        every write, else why not."""
        ...


@dataclass(frozen=True, slots=True)
class Wire:
    """A kind of Modbus driver: its `kind:` in the io image and how its transport is made."""

    kind: str
    transport: Callable[[DriverSpec, IoPlan], Transport]


class TcpTransport:
    """Modbus TCP: one connection of the I/O thread's own; the direct write opens a fresh one."""

    def __init__(self, params: ModbusParams) -> None:
        self.params = params
        self.where = f"{params.host}:{params.port}"
        self.silence = (f"unit {params.unit} at {self.where} did not answer within "
                        f"{params.timeout_s:g} s")

    def client(self, on_link: OnLink) -> Client:
        p = self.params
        client: Client = AsyncModbusTcpClient(
            p.host,
            port=p.port,
            timeout=p.timeout_s,
            retries=0,
            reconnect_delay=0,  # reconnection and its backoff are modbus_link's
            trace_connect=on_link,
        )
        return client

    def attach(self) -> None:
        """Nothing shared: every driver has its own connection."""

    def detach(self) -> None:
        """Nothing shared."""

    def write_direct(self, blocks: Sequence[Block], outputs: Sequence[list[Any]],
                     deadline: float) -> str:
        left = deadline - time.monotonic()
        if left <= 0:
            return "no time left for a direct write"
        p = self.params
        client = ModbusTcpClient(p.host, port=p.port, timeout=min(p.timeout_s, left),
                                 retries=0, reconnect_delay=0)
        try:
            if not client.connect():  # type: ignore[no-untyped-call]
                return f"cannot connect to {self.where}"
            write_all(client, p.unit, blocks, outputs)
        except ERRORS as exc:
            return f"direct write: {exc or type(exc).__name__}"
        finally:
            client.close()  # type: ignore[no-untyped-call]
        return ""


def _tcp(spec: DriverSpec, plan: IoPlan) -> Transport:
    return TcpTransport(ModbusParams.from_spec(spec, plan))


TCP = Wire("modbus", _tcp)
