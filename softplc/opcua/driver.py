"""`kind: opcua` remote I/O: variables of any OPC UA server mapped to symbols, and output
symbols bound to remote methods (the seed paper's CG: a net calls a service of another
component).

Owns: the channel syntax, the I/O thread with its own asyncio loop and asyncua client, the
last good inputs, the latest outputs, method calls on rising edges with their done/failed
inputs, health, problem(), go_safe(). Values move typed (typed.py): a remote Float into a
`real`, a `dint` written as the remote variable's DataType; never wrapped.
Does not know: the scan, the Petri net, the local OPC UA server.

Channels (the symbol's `channel:`):
  `PLC.Symbols.s1_i` or `ns=2;s=...`/`i=85`  a variable; a bare name is a string id in the
                                            driver's `namespace` (default urn:softplc)
  `call:PLC.Program.Start`                  (bool output) a rising edge calls that method on
                                            its parent object (the id before the last dot)
  `done:SYMBOL` / `failed:SYMBOL`           (bool input) true once the call of output SYMBOL
                                            succeeded / was refused; both clear when it falls

Threading as devices/modbus_io.py: read_inputs/write_outputs only swap values under a lock
and wake the I/O thread; the network is touched only there, so the scan never blocks.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

from asyncua import Client, ua

from softplc.core.image import ProcessImage
from softplc.core.symbols import Direction, DriverSpec, Symbol, SymType
from softplc.devices.driver import Health
from softplc.opcua.client import RefusingAwareClient
from softplc.opcua.typed import VARIANT_TYPES, remote_raw, remote_variant

log = logging.getLogger(__name__)

PARAMS: Final = ("url", "namespace", "user", "password_env", "timeout_s", "reconnect_s")
CLOSE_JOIN_S: Final = 2.0


@dataclass(frozen=True, slots=True)
class Binding:
    symbol: Symbol
    kind: str  # "var", "call", "done", "failed"
    target: str  # node id text, or the output symbol of done/failed


def parse_bindings(spec: DriverSpec, symbols: Sequence[Symbol]) -> list[Binding]:
    """Every symbol's channel, checked; one ValueError lists every problem."""
    out, issues = [], []
    outputs = {s.name for s in symbols if s.direction is Direction.OUT}
    for sym in symbols:
        kind, sep, rest = (sym.channel or "").partition(":")
        if not sep or kind not in ("call", "done", "failed"):
            kind, rest = "var", sym.channel or sym.name
        problem = None
        if kind != "var" and sym.type is not SymType.BOOL:
            problem = f"{kind}: needs a bool symbol"
        elif kind == "call" and sym.direction is not Direction.OUT:
            problem = "call: needs an output symbol (%QX)"
        elif kind in ("done", "failed") and (sym.direction is not Direction.IN
                                             or rest not in outputs):
            problem = f"{kind}: needs an input symbol and an output symbol of this driver"
        elif kind == "var" and sym.direction is Direction.MEMORY:
            problem = "memory is not I/O: expected an input or output"
        if problem:
            issues.append(f"symbol {sym.name!r} (line {sym.line}): {problem}")
        out.append(Binding(sym, kind, rest.strip()))
    if issues:
        raise ValueError(f"driver {spec.name!r} (opcua):\n  " + "\n  ".join(issues))
    return out


class OpcUaIoDriver:
    """One remote OPC UA server as a device (see the module docstring)."""

    def __init__(self, spec: DriverSpec, symbols: Sequence[Symbol]) -> None:
        unknown = sorted(set(spec.params) - set(PARAMS))
        if unknown or "url" not in spec.params:
            raise ValueError(f"driver {spec.name!r}: params {sorted(PARAMS)} (url required), "
                             f"unknown {unknown}")
        self.name = spec.name
        self.spec = spec  # what the runtime opened, for the start-up gate (docs/faults.md)
        self.params = dict(spec.params)
        self.bindings = parse_bindings(spec, symbols)
        self._lock = threading.Lock()
        self._inputs: dict[str, int] = {}  # symbol -> value (I/O thread writes)
        self._outputs: dict[str, int] = {}  # symbol -> value (scan writes)
        self._vtypes: dict[str, ua.VariantType] = {}  # output symbol -> remote DataType
        self._calls: dict[str, str] = {}  # output symbol -> "", "done", "failed"
        self._cycles = 0
        self._delivered = False  # read_inputs copied one completed cycle's inputs since open()
        self._ok = False
        self._connected = False
        self._error = ""
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._task: asyncio.Task[None] | None = None
        self._cycle_done = threading.Condition(self._lock)

    # ----- scan side -----

    def open(self) -> None:
        if self._thread is not None:
            return
        logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # our logger says what matters
        with self._lock:  # inputs of an earlier opening are not this one's first image
            self._inputs, self._cycles, self._delivered = {}, 0, False
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._main, name=f"opcua-io-{self.name}",
                                        daemon=True)
        self._thread.start()

    def close(self) -> None:
        thread, loop = self._thread, self._loop
        self._thread = self._loop = None
        if thread is None or loop is None:
            return
        task = self._task
        if task is not None:
            with contextlib.suppress(RuntimeError):  # the loop has already ended
                loop.call_soon_threadsafe(task.cancel)
        thread.join(CLOSE_JOIN_S)
        if thread.is_alive():
            log.warning("opcua driver %s: I/O thread did not stop in %ss", self.name, CLOSE_JOIN_S)

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        with self._lock:
            values = dict(self._inputs)
            calls = dict(self._calls)
            cycled = self._cycles > 0
        for b in self.bindings:
            if b.kind == "var" and b.symbol.direction is Direction.IN and b.symbol.name in values:
                image.set(b.symbol.address, values[b.symbol.name])
            elif b.kind in ("done", "failed"):
                image.set(b.symbol.address, int(calls.get(b.target) == b.kind))
        self._delivered = self._delivered or cycled

    def delivered(self) -> bool:
        """Has read_inputs copied the inputs of one completed cycle since open()? (Health
        alone cannot say: a cycle may complete between the copy and health().)"""
        return self._delivered

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        outputs = {b.symbol.name: image.get(b.symbol.address) for b in self.bindings
                   if b.kind in ("var", "call") and b.symbol.direction is Direction.OUT}
        with self._lock:
            self._outputs = outputs
        self._trigger()

    def health(self) -> Health:
        with self._lock:
            if self._thread is None or not self._connected:
                return Health.DOWN
            return Health.OK if self._ok else Health.DEGRADED

    def problem(self) -> str:
        with self._lock:
            if self._connected and self._ok:
                return ""
            return self._error or f"not connected to {self.params['url']}"

    def go_safe(self, image: ProcessImage, timeout_s: float) -> bool:
        """Write `image`'s outputs now and wait (at most timeout_s) until a cycle has
        written them; True when acknowledged by the remote server."""
        with self._lock:
            target = self._cycles + 2  # a cycle already running may hold the old outputs
        self.write_outputs(image, 0)
        with self._cycle_done:
            return self._cycle_done.wait_for(
                lambda: self._cycles >= target and self._ok, timeout_s)

    def _trigger(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(wake.set)

    # ----- I/O thread -----

    def _main(self) -> None:
        loop = self._loop
        assert loop is not None
        asyncio.set_event_loop(loop)
        self._task = task = loop.create_task(self._run())
        try:
            with contextlib.suppress(asyncio.CancelledError):
                loop.run_until_complete(task)  # ends when close() cancels it
        finally:
            pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
            for leftover in pending:  # the client's own watchdog tasks
                leftover.cancel()
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _run(self) -> None:
        self._wake = asyncio.Event()
        timeout_s = float(self.params.get("timeout_s", 2.0))
        while True:
            # asyncua probes the server every second and drops the connection when one
            # probe takes longer than that: a remote is lost after timeout_s, as for reads.
            client = RefusingAwareClient(str(self.params["url"]), timeout=timeout_s,
                                         watchdog_intervall=timeout_s)
            if self.params.get("user"):
                client.set_user(str(self.params["user"]))
                client.set_password(os.environ.get(str(self.params.get("password_env", "")), ""))
            try:
                await client.connect()
                nodes = await self._resolve(client)
                self._note(connected=True, ok=False, error="")
                await self._cycles_on(client, nodes)
            except (OSError, TimeoutError, ua.UaError) as exc:
                self._note(connected=False, ok=False, error=f"{type(exc).__name__}: {exc}")
            finally:
                with contextlib.suppress(Exception):
                    await asyncio.wait_for(client.disconnect(), 1.0)
            await asyncio.sleep(float(self.params.get("reconnect_s", 0.5)))

    async def _resolve(self, client: Client) -> dict[str, Any]:
        ns = await client.get_namespace_index(str(self.params.get("namespace", "urn:softplc")))
        nodes: dict[str, Any] = {}
        self._vtypes = {}
        for b in self.bindings:
            if b.kind in ("var", "call"):
                text = b.target
                if not text.startswith(("ns=", "i=", "s=", "g=", "b=")):
                    text = f"ns={ns};s={text}"
                nodes[b.symbol.name] = node = client.get_node(text)
                if b.kind == "var" and b.symbol.direction is Direction.OUT:
                    self._vtypes[b.symbol.name] = await _data_type(node, b.symbol)
        return nodes

    async def _cycles_on(self, client: Client, nodes: dict[str, Any]) -> None:
        assert self._wake is not None
        written: dict[str, int] = {}
        inputs = [b for b in self.bindings if b.kind == "var" and b.symbol.direction is
                  Direction.IN]
        while True:
            with contextlib.suppress(TimeoutError):  # no scan woke us: read inputs anyway
                await asyncio.wait_for(self._wake.wait(), 0.1)
            self._wake.clear()
            with self._lock:
                outputs = dict(self._outputs)
            problems: list[str] = []
            for b in self.bindings:
                name = b.symbol.name
                if name not in outputs or written.get(name) == outputs[name]:
                    continue
                if b.kind == "var":
                    try:
                        variant = remote_variant(b.symbol.type, outputs[name], self._vtypes[name])
                    except ValueError as exc:  # not written: the remote keeps its value
                        problems.append(f"output {name} not written to {b.target}: {exc}")
                        continue
                    await nodes[name].write_value(variant)
                elif b.kind == "call":
                    await self._edge(client, nodes[name], name, bool(outputs[name]))
                written[name] = outputs[name]
            values = await client.read_values([nodes[b.symbol.name] for b in inputs])
            fresh = {}
            for b, value in zip(inputs, values, strict=True):
                try:
                    fresh[b.symbol.name] = remote_raw(b.symbol.type, value)
                except ValueError as exc:  # the input keeps its last good value
                    problems.append(f"input {b.symbol.name} from {b.target}: {exc}")
            self._cycle(fresh, problems)

    def _cycle(self, fresh: dict[str, int], problems: list[str]) -> None:
        """A cycle's inputs; one whose values did not fit is DEGRADED (the fault policy
        decides), its text in problem()."""
        text = "; ".join(problems[:3])
        with self._cycle_done:
            self._inputs = {**self._inputs, **fresh}
            self._cycles += 1
            self._ok = not problems
            logged, self._error = self._error, text or self._error
            self._cycle_done.notify_all()
        if text and text != logged:
            log.warning("opcua driver %s: %s", self.name, text)

    async def _edge(self, client: Client, node: Any, name: str, high: bool) -> None:
        """Rising edge: call the method on its parent; falling edge: clear done/failed."""
        if not high:
            with self._lock:
                self._calls[name] = ""
            return
        parent = await node.get_parent()
        try:
            await parent.call_method(node)
            result = "done"
        except ua.UaStatusCodeError as exc:  # refused: an event for the net, not a crash
            log.warning("opcua driver %s: call %s refused: %s", self.name, name, exc)
            result = "failed"
        with self._lock:
            self._calls[name] = result

    def _note(self, *, connected: bool, ok: bool, error: str) -> None:
        with self._cycle_done:
            changed = connected != self._connected
            self._connected, self._ok = connected, ok
            if error:
                self._error = error
            self._cycle_done.notify_all()
        if changed or error:
            log.info("opcua driver %s: %s", self.name, error or "connected")


async def _data_type(node: Any, symbol: Symbol) -> ua.VariantType:
    """The remote variable's DataType, which a write must carry (a softplc refuses any
    other); the symbol's own (typed.py) when the remote one is abstract (Number) or
    unreadable."""
    with contextlib.suppress(ua.UaError, ValueError):
        vtype: ua.VariantType = await node.read_data_type_as_variant_type()
        if vtype is not ua.VariantType.Variant:
            return vtype
    return VARIANT_TYPES[symbol.type]
