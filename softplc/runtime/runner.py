"""One scan with its devices: read inputs through the drivers, scan, write outputs, trace.

Owns: opening the drivers an io image declares, the per-scan sequence around core.scan (with
the device fault policy of core/faults.py fed from the drivers' health), and the trace
record of each scan. Used by the real-time loop and by virtual-time simulation.
Does not know: which clock drives it, processes, sockets.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

from softplc.core.faults import DeviceMonitor
from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command
from softplc.core.net import CompiledNet
from softplc.core.scan import Plc, ProgramCommand, ScanResult, scan
from softplc.core.snapshot import HmiWrite
from softplc.core.symbols import FaultPolicy, IoImage
from softplc.devices.driver import Diagnosed, Driver, Health
from softplc.runtime.trace import TraceWriter, image_digest, input_changes


def open_drivers(io: IoImage, seed: int = 0, plant: str | None = None) -> list[Driver]:
    """The drivers `io` declares, opened. `plant` replaces the plant model of sim drivers."""
    drivers: list[Driver] = []
    symbols = list(io.symbols.values())
    for spec in io.drivers.values():
        if spec.kind == "sim":
            from softplc.devices.plants.registry import make_plant
            from softplc.devices.sim import SimDriver

            model = make_plant(plant, seed) if plant else None
            drivers.append(SimDriver(spec, symbols, plant=model, seed=seed))
        elif spec.kind == "modbus":
            from softplc.devices.modbus_io import ModbusIoDriver

            drivers.append(ModbusIoDriver(spec, [s for s in symbols if s.driver == spec.name]))
        elif spec.kind == "opcua":
            from softplc.opcua.driver import OpcUaIoDriver

            drivers.append(OpcUaIoDriver(spec, [s for s in symbols if s.driver == spec.name]))
    for driver in drivers:
        driver.open()
    return drivers


class ScanRunner:
    """The PLC with its drivers. `step()` runs one scan at `now_ns`."""

    def __init__(self, plc: Plc, drivers: Sequence[Driver], trace: TraceWriter | None = None) -> None:
        self.plc = plc
        self.drivers = list(drivers)
        self.inputs = ProcessImage(plc.image.sizes)
        self.trace = trace
        self._last_inputs: ProcessImage | None = None
        self._digest = ""
        self.fired_counts: dict[str, int] = {}
        self.devices = DeviceMonitor()
        self._policies_of: CompiledNet | None = None
        self._policy_map: dict[str, FaultPolicy] = {}

    def set_drivers(self, drivers: Sequence[Driver]) -> None:
        for driver in self.drivers:
            driver.close()
        self.drivers = list(drivers)
        self.devices.forget()
        self.inputs = ProcessImage(self.plc.image.sizes)
        self._last_inputs = None

    def health(self) -> dict[str, Health]:
        return {d.name: d.health() for d in self.drivers}

    def device_report(self) -> dict[str, dict[str, object]]:
        """Per driver: the fault policy's verdict, scans without an answer, and why."""
        return self.devices.report()

    def step(self, now_ns: int, commands: Sequence[ProgramCommand] = (),
             hmi: Sequence[HmiWrite] = (), timing: dict[str, int] | None = None) -> ScanResult:
        for driver in self.drivers:
            driver.read_inputs(self.inputs, now_ns)
        before = self._check_devices(now_ns) if self.drivers else []
        result = scan(self.plc, self.inputs, now_ns, commands, hmi)
        after = self.devices.after_scan(self.plc, now_ns) if self.drivers else []
        if before or after:
            result = replace(result, events=(*before, *result.events, *after), outputs_changed=True)
        for driver in self.drivers:
            driver.write_outputs(result.outputs, now_ns)
        for name in result.fired:
            self.fired_counts[name] = self.fired_counts.get(name, 0) + 1
        if self.trace is not None:
            self.trace.record(self._record(now_ns, commands, hmi, result), timing)
        if self._last_inputs is None:
            self._last_inputs = self.inputs.copy()
        else:
            self.inputs.copy_into(self._last_inputs)
        return result

    def _check_devices(self, now_ns: int) -> list[str]:
        # Health after read_inputs: the inputs this scan uses are the ones it judges.
        answering = {d.name: d.health() is Health.OK for d in self.drivers}
        return self.devices.before_scan(self.plc, answering, self._policies(), self._why, now_ns)

    def _policies(self) -> Mapping[str, FaultPolicy]:
        net = self.plc.net
        if net is None:
            return {}
        if self._policies_of is not net:  # once per program, not once per scan
            self._policies_of = net
            self._policy_map = {name: spec.policy for name, spec in net.io.drivers.items()}
        return self._policy_map

    def _why(self, name: str) -> str:
        driver = next(d for d in self.drivers if d.name == name)
        if isinstance(driver, Diagnosed):
            return driver.problem() or driver.health().value
        return driver.health().value

    def _record(self, now_ns: int, commands: Sequence[ProgramCommand],
                hmi: Sequence[HmiWrite], result: ScanResult) -> dict[str, Any]:
        record: dict[str, Any] = {"k": self.plc.scan_count - 1, "t": now_ns,
                                  "in": input_changes(self.inputs, self._last_inputs),
                                  "out": self._output_digest(result), "state": self.plc.state.name}
        if commands:
            record["cmd"] = [_command(c) for c in commands]
        if hmi:
            record["hmi"] = [[str(w.address), list(w.values)] for w in hmi]
        if result.fired:
            record["fired"] = list(result.fired)
        if result.completed:
            record["done"] = list(result.completed)
        if result.marking_changes:
            record["m"] = result.marking_changes
        if result.events:
            record["ev"] = list(result.events)
        return record

    def _output_digest(self, result: ScanResult) -> str:
        if result.outputs_changed or not self._digest:
            self._digest = image_digest(result.outputs)
        return self._digest

    def close(self) -> None:
        for driver in self.drivers:
            driver.close()
        self.devices.forget()  # a closed device is not a failed one; reopened, it boots again
        if self.trace is not None:
            self.trace.close()


def _command(cmd: ProgramCommand) -> dict[str, Any]:
    out: dict[str, Any] = {"c": cmd.command.value}
    if cmd.net is not None:
        out["program"] = cmd.net.name
        out["hash"] = cmd.net.program_hash
    if cmd.online:
        out["online"] = True
    return out


def boot(net: CompiledNet, seed: int = 0, start: bool = True, trace: TraceWriter | None = None,
         plant: str | None = None) -> tuple[ScanRunner, list[ProgramCommand]]:
    """A runner for `net` and the commands that download (and start) it on the first scan."""
    plc = Plc.empty(ProcessImage(net.io.sizes))
    runner = ScanRunner(plc, open_drivers(net.io, seed, plant), trace)
    commands = [ProgramCommand(Command.DOWNLOAD, net, id=1)]
    if start:
        commands.append(ProgramCommand(Command.START, id=2))
    return runner, commands
