"""Static checks of an io image's drivers and channels: what opening them would refuse, found
without opening anything (no socket, no thread, no plant advanced).

Owns: the device part of `softplc check` and of `softplc simulate`'s checks before it runs:
a sim driver names a known plant and only channels that plant has (sensors for inputs,
actuators for outputs); a Modbus driver has valid parameters and channels (syntax, table for
the symbol's area, offset range, no channel used twice). Every problem is located
(FILE:LINE of the symbols file) and offers the closest known name when there is one.
Does not know: the program, clocks, the scan.
"""

from __future__ import annotations

from collections.abc import Sequence

from softplc.core.problems import Problem
from softplc.core.symbols import Direction, DriverSpec, IoImage, Symbol
from softplc.devices.plants.registry import PLANTS, make_plant
from softplc.program.suggest import did_you_mean, did_you_mean_key

SIM_PARAMS = ("plant",)


def check_devices(io: IoImage, plant: str | None = None, need_plant: bool = True
                  ) -> list[Problem]:
    """Every problem the drivers of `io` would raise when opened, sorted by line. `plant` is
    the plant of sim drivers that name none, as `--plant` is for run and simulate. Without
    `need_plant`, a sim driver with no plant at all is not a problem (`check` cannot know the
    --plant of a later run) and its channels are not checked."""
    problems: list[Problem] = []
    for spec in io.drivers.values():
        mine = [s for s in io.symbols.values() if s.driver == spec.name]
        if spec.kind == "sim" and (need_plant or plant or spec.params.get("plant")):
            problems += _check_sim(io.path, spec, mine, plant)
        elif spec.kind in ("modbus", "modbus_rtu"):
            problems += _check_modbus(io.path, spec, mine)
    return sorted(problems)


def _check_sim(file: str, spec: DriverSpec, symbols: Sequence[Symbol],
               override: str | None) -> list[Problem]:
    path = f"drivers.{spec.name}"
    problems = [Problem(file, spec.line, f"{path}.{key}", f"unknown key {key!r}"
                        f"{did_you_mean_key(key, SIM_PARAMS)}; a sim driver takes: plant")
                for key in sorted(set(spec.params) - set(SIM_PARAMS))]
    # The io image's plant wins; --plant serves sim drivers that name none (runner.open_drivers)
    # and contradicting the io image is refused, as `softplc run` does.
    own = spec.params.get("plant")
    if override and own and own != override:
        problems.append(Problem(file, spec.line, path, f"names plant {own!r}, --plant asks for "
                                f"{override!r}: drop --plant or use an io image for that plant"))
    name = own if own else override
    known = ", ".join(sorted(PLANTS))
    if not isinstance(name, str):
        problems.append(Problem(file, spec.line, path,
                                f"a sim driver needs plant: NAME (one of {known})"))
        return problems
    if name not in PLANTS:
        where = "plant" if own else "--plant"
        problems.append(Problem(file, spec.line, path, f"{where} {name!r}: no such plant model"
                                f"{did_you_mean(name, PLANTS)}; known plants: {known}"))
        return problems
    model = make_plant(name)  # pure physics at t=0: only its signal lists are read
    for sym in symbols:
        if sym.direction is Direction.IN:
            signals, role = model.sensors, "sensor"
        elif sym.direction is Direction.OUT:
            signals, role = model.actuators, "actuator"
        else:
            continue  # memory is never read or written by a sim driver
        channel = str(sym.channel)
        if channel in signals:
            continue
        implied = " (the symbol's name: no channel: given)" if channel == sym.name else ""
        problems.append(Problem(
            file, sym.line, f"symbols.{sym.name}",
            f"channel {channel!r}{implied} is not a{'n' if role == 'actuator' else ''} {role} "
            f"of plant {name!r}{did_you_mean(channel, signals)}; its {role}s: "
            f"{', '.join(signals)}"))
    return problems


def _check_modbus(file: str, spec: DriverSpec, symbols: Sequence[Symbol]) -> list[Problem]:
    # Imported here: pymodbus is loaded only for io images that have a Modbus driver.
    from softplc.devices.modbus_io import ModbusParams, channel_problems
    from softplc.devices.modbus_rtu import RtuParams

    problems = []
    try:
        (RtuParams if spec.kind == "modbus_rtu" else ModbusParams).from_spec(spec)
    except (TypeError, ValueError) as exc:
        problems.append(Problem(file, spec.line, f"drivers.{spec.name}", str(exc)))
    problems += [Problem(file, sym.line, f"symbols.{sym.name}", f"driver {spec.name}: {issue}")
                 for sym, issue in channel_problems(symbols)]
    return problems
