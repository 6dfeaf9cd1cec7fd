"""One scan with its devices: read inputs through the drivers, scan, write outputs, trace.

Owns: opening the drivers an io image declares, the per-scan sequence around core.scan (with
the device fault policy of core/faults.py fed from the drivers' health), and the trace
record of each scan. Used by the real-time loop and by virtual-time simulation.
Does not know: which clock drives it, processes, sockets.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any

from softplc.core.faults import DeviceMonitor
from softplc.core.image import ProcessImage
from softplc.core.judge import NOTHING_OBSERVED, Observed, judge
from softplc.core.lifecycle import Command, PlcState
from softplc.core.net import CompiledNet
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.result import ScanResult
from softplc.core.scan import scan
from softplc.core.snapshot import HmiWrite
from softplc.core.symbols import DriverSpec, IoImage
from softplc.devices.driver import Diagnosed, Driver, Health, go_safe_all
from softplc.runtime.trace import TraceWriter, image_digest, input_changes


def open_drivers(io: IoImage, seed: int = 0, plant: str | None = None) -> list[Driver]:
    """The drivers `io` declares, opened. `plant` is the plant model of sim drivers whose io
    image names none: an io image that names its plant keeps it (see plant_conflict). A driver
    that cannot be opened raises DeviceError (or ValueError for an unknown plant); the ones
    opened before it are closed again."""
    drivers: list[Driver] = []
    symbols = list(io.symbols.values())
    try:
        for spec in io.drivers.values():
            if spec.kind == "sim":
                from softplc.devices.plants.registry import make_plant
                from softplc.devices.sim import SimDriver

                own = spec.params.get("plant")
                model = make_plant(plant, seed) if plant and not own else None
                drivers.append(SimDriver(spec, symbols, plant=model, seed=seed))
            elif spec.kind == "modbus":
                from softplc.devices.modbus_io import ModbusIoDriver

                drivers.append(ModbusIoDriver(spec, [s for s in symbols if s.driver == spec.name]))
            elif spec.kind == "modbus_rtu":
                from softplc.devices.modbus_rtu import ModbusRtuDriver

                drivers.append(ModbusRtuDriver(spec, [s for s in symbols if s.driver == spec.name]))
            elif spec.kind == "opcua":
                from softplc.opcua.driver import OpcUaIoDriver

                drivers.append(OpcUaIoDriver(spec, [s for s in symbols if s.driver == spec.name]))
            else:
                continue
            drivers[-1].open()
    except BaseException:
        for driver in drivers:
            driver.close()
        raise
    return drivers


def plant_conflict(io: IoImage, plant: str | None) -> str | None:
    """Why `--plant plant` cannot run this io image (its sim driver names another plant), or
    None. The io image wins over the flag; a contradiction is refused, never guessed."""
    for spec in io.drivers.values():
        own = spec.params.get("plant")
        if spec.kind == "sim" and plant and own and own != plant:
            return (f"{io.path}: sim driver {spec.name} names plant {own!r}, "
                    f"--plant asks for {plant!r}: drop --plant (the io image's plant is used) "
                    "or use an io image for that plant")
    return None


class ScanRunner:
    """The PLC with its drivers. `step()` runs one scan at `now_ns`."""

    def __init__(self, plc: Plc, drivers: Sequence[Driver],
                 trace: TraceWriter | None = None) -> None:
        self.plc = plc
        self.drivers = list(drivers)
        self.inputs = ProcessImage(plc.image.sizes)
        self.trace = trace
        self._traced_out: dict[str, int] = {}  # output symbols as the trace last gave them
        self._traced_diag = 0
        self._traced_net: CompiledNet | None = None  # the net whose outputs _traced_out holds
        self._last_inputs: ProcessImage | None = None
        self._last_in: bytes | None = None  # _last_inputs' input areas, as bytes
        self._digest = ""
        self.fired_counts: dict[str, int] = {}
        self._noted: Observed | None = None  # judged between scans; traced with the next one
        self._raised: dict[str, str] = {}  # drivers whose call raised this scan, and how
        self._steady = NOTHING_OBSERVED  # every device answering, as last observed
        self._state_seen: PlcState | None = None  # the state whose name _state_name is
        self._state_name = ""
        self._open = opened(self.drivers)  # the PLC's view of them (its start-up gate)

    def sim_plants(self) -> dict[str, object]:
        """The simulated plants behind the drivers, by driver name (retain keeps them)."""
        return {d.name: d.plant for d in self.drivers if hasattr(d, "plant")}

    def set_drivers(self, drivers: Sequence[Driver]) -> None:
        for driver in self.drivers:
            driver.close()
        self.drivers = list(drivers)
        self._open = opened(self.drivers)
        self._steady = NOTHING_OBSERVED  # other devices: their first answers are judged anew
        self.devices.forget()
        self.inputs = ProcessImage(self.plc.image.sizes)
        self._last_inputs = self._last_in = None

    @property
    def devices(self) -> DeviceMonitor:
        return self.plc.devices

    def health(self) -> dict[str, Health]:
        return {d.name: d.health() for d in self.drivers}

    def device_report(self) -> dict[str, dict[str, object]]:
        """Per driver: the fault policy's verdict, scans without an answer, and why."""
        return self.devices.report()

    def _extra(self, result: ScanResult) -> dict[str, Any]:
        """The trace's readable part: output symbols whose value changed since the last
        traced scan (so replay names what differs), and the scan's new diagnostics."""
        extra: dict[str, Any] = {}
        net, engine, outputs = self.plc.net, self.plc.engine, result.outputs
        if net is not None and (result.outputs_changed or net is not self._traced_net):
            self._traced_net = net  # an unchanged output image has the values traced last
            changed = {}
            for symbol in net.io.symbols.values():
                if symbol.direction.value == "out":
                    value = int(outputs.get(symbol.address))
                    if self._traced_out.get(symbol.name) != value:
                        changed[symbol.name] = self._traced_out[symbol.name] = value
            if changed:
                extra["q"] = changed
        if engine is not None and engine.diagnostic_count > self._traced_diag:
            extra["diag"] = engine.diagnostics[self._traced_diag:engine.diagnostic_count]
            self._traced_diag = engine.diagnostic_count
        return extra

    def step(self, now_ns: int, commands: Sequence[ProgramCommand] = (),
             hmi: Sequence[HmiWrite] = (), observed: Observed = NOTHING_OBSERVED
             ) -> ScanResult:
        """Read inputs, scan, write outputs, trace. A driver that raises is a device that did
        not answer this scan (its exception is the reason): the PLC never dies of a driver."""
        for driver in self.drivers:
            try:
                driver.read_inputs(self.inputs, now_ns)
            except Exception as exc:
                self._raised[driver.name] = f"read raised {type(exc).__name__}: {exc}"
        if self.drivers:
            observed = self._observe(observed)
        if self.plc.open_devices is not self._open:  # a Plc put in by a warm start, a test
            self.plc.open_devices = self._open
        result = scan(self.plc, self.inputs, now_ns, commands, hmi, observed)
        self._write(result.outputs, now_ns)
        for name in result.fired:
            self.fired_counts[name] = self.fired_counts.get(name, 0) + 1
        if self.trace is not None:
            self._trace(self.trace, now_ns, commands, hmi, result, observed)
        return result

    def _write(self, outputs: ProcessImage, now_ns: int) -> None:
        for driver in self.drivers:
            try:
                driver.write_outputs(outputs, now_ns)
            except Exception as exc:
                self._raised[driver.name] = f"write raised {type(exc).__name__}: {exc}"

    def judge_now(self, observed: Observed, now_ns: int) -> list[str]:
        """A measurement judged between scans (the watchdog): the PLC decides at once and the
        drivers get its outputs at once; the trace carries it with the next scan."""
        events = judge(self.plc, observed, now_ns)
        self._noted = observed
        if events:
            self.go_safe(now_ns)
        return events

    def go_safe(self, now_ns: int, timeout_s: float = 0.5) -> list[str]:
        """The PLC's output image (safe values, unless RUNNING) to every device now, confirmed
        by the devices within one shared bound; returns the devices that did not confirm."""
        if not self.drivers:
            return []
        confirmed = go_safe_all(self.drivers, self.plc.image, timeout_s)
        return sorted(name for name, ok in confirmed.items() if not ok)

    def _observe(self, observed: Observed) -> Observed:
        # Health after read_inputs: the inputs this scan uses are the ones it judges.
        raised = self._raised
        steady = self._steady
        if (not raised and not observed.overrun and not observed.stall
                and len(steady.answering) == len(self.drivers)):
            for driver in self.drivers:
                if driver.health() is not Health.OK:
                    break
            else:  # every device answers, as in the last such scan: no dictionary to build
                return steady
        if raised:
            self._raised = {}
        answering = {d.name: d.health() is Health.OK and d.name not in raised and delivered(d)
                     for d in self.drivers}
        if not observed.overrun and not observed.stall and answering == self._steady.answering:
            return self._steady  # every device answers: the Observed of the last such scan
        why = {}
        if not all(answering.values()):
            why = {name: raised.get(name) or self._why(name)
                   for name, ok in answering.items() if not ok}
        result = Observed(answering, why, observed.overrun, observed.stall)
        if not why and not observed.overrun and not observed.stall:
            self._steady = result
        return result

    def _why(self, name: str) -> str:
        driver = next(d for d in self.drivers if d.name == name)
        if isinstance(driver, Diagnosed):
            return driver.problem() or driver.health().value
        return driver.health().value

    def _trace(self, trace: TraceWriter, now_ns: int, commands: Sequence[ProgramCommand],
               hmi: Sequence[HmiWrite], result: ScanResult, observed: Observed) -> None:
        """The scan's trace record; a scan in which only time passed takes the short way
        (TraceWriter.steady: the same line, no dictionary, no encoder)."""
        extra = self._extra(result) if trace.writes_file else None
        inputs = self._input_changes()
        digest = self._output_digest(result)
        # Devices the scan waited for that it could not observe: not open yet (issue 26).
        unopened = [n for n in self.plc.waiting_io if n not in observed.answering] \
            if self.plc.waiting_io else []
        steady_obs = self._noted is None and not unopened and (observed is self._steady or (
            observed is NOTHING_OBSERVED and not self._declared()))
        if (steady_obs and not extra and not inputs and not commands and not hmi
                and not result.fired and not result.completed and not result.marking_changes
                and not result.events):
            state = self.plc.state
            if state is not self._state_seen:  # Enum.name is a descriptor call: once per state
                self._state_seen, self._state_name = state, state.name
            trace.steady(self.plc.scan_count - 1, now_ns, digest, self._state_name)
            return
        record: dict[str, Any] = {"k": self.plc.scan_count - 1, "t": now_ns,
                                  "in": inputs, "out": digest, "state": self.plc.state.name}
        obs = _observation(observed, self._noted, self._declared())
        if unopened:
            obs["wait"] = unopened
        self._noted = None
        if obs:
            record["obs"] = obs
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
        trace.record(record, None, extra)

    def _declared(self) -> Collection[str]:
        """The drivers the PLC's program declares: the devices replay assumes observed."""
        net = self.plc.net
        return () if net is None else net.io.drivers

    def _input_changes(self) -> dict[str, dict[str, int]]:
        """The inputs that differ from the last traced scan's, which this scan's become."""
        now = self.inputs.inputs_bytes()
        if now == self._last_in:
            return {}  # the steady scan: one comparison, nothing copied
        changes = input_changes(self.inputs, self._last_inputs)
        if self._last_inputs is None:
            self._last_inputs = self.inputs.copy()
        else:
            self.inputs.copy_into(self._last_inputs)
        self._last_in = now
        return changes

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


def _observation(observed: Observed, noted: Observed | None,
                 declared: Collection[str]) -> dict[str, Any]:
    """The judged measurements of one scan as a trace entry ({} in the steady state). The
    devices observed are named unless they are the program's declared drivers (what replay
    assumes): the scan of a download runs before its devices are opened (issue 26.6)."""
    obs: dict[str, Any] = {}
    silent = {name: observed.why.get(name, "") for name, ok in observed.answering.items()
              if not ok}
    if silent:
        obs["dev"] = silent
    if silent or list(observed.answering) != list(declared):
        obs["devs"] = sorted(observed.answering)
    for source in (noted, observed):
        if source is not None and source.overrun:
            obs["overrun"] = source.overrun
        if source is not None and source.stall:
            obs["stall"] = source.stall
    return obs


def opened(drivers: Sequence[Driver]) -> dict[str, DriverSpec | None]:
    """Name -> the spec each driver was opened from (None: a driver that does not say, such
    as simulate's script inputs): what the PLC's start-up gate compares its io image with."""
    return {d.name: spec if isinstance(spec := getattr(d, "spec", None), DriverSpec) else None
            for d in drivers}


def delivered(driver: Driver) -> bool:
    """A driver's first input image has reached the image (docs/faults.md, start-up); a
    driver without delivered() delivers in every read it answers."""
    check = getattr(driver, "delivered", None)
    return check is None or bool(check())


def observed_from(obs: dict[str, Any], drivers: Sequence[str]) -> Observed:
    """The Observed a trace entry stands for (replay); `drivers` answer unless listed."""
    silent = dict(obs.get("dev", {}))
    names = list(obs.get("devs", drivers))  # []: none observed
    for name in obs.get("wait", ()):  # not open yet: the scan waited for its first image
        silent.setdefault(name, "not open yet")
        names += [] if name in names else [name]
    answering = {name: name not in silent for name in names}
    return Observed(answering, silent, obs.get("overrun", ""), obs.get("stall", ""))


def _command(cmd: ProgramCommand) -> dict[str, Any]:
    out: dict[str, Any] = {"c": cmd.command.value}
    if cmd.net is not None:
        out["program"] = cmd.net.name
        out["hash"] = cmd.net.program_hash
    if cmd.online:
        out["online"] = True
    if cmd.command in (Command.FORCE, Command.UNFORCE):  # replay reproduces forces
        out["symbol"], out["value"] = cmd.symbol, cmd.value
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
