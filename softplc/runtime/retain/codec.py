"""The PLC's retained state as a document: taken at a scan boundary, encoded for a file, and
put back into a PLC at a warm restart.

Owns: what is retained (marking, coloured tokens, timers, the image's outputs and %M memory,
the lifecycle state, scan count and scan clock, program name and hash, forces; a sim plant's
state, labelled simulation-only), Capture (cheap copies taken by the scan thread), encode
(by the writer thread, every token value checked so that a bad one is named, never a
TypeError from deep inside json), restore, and unpickling plants from an allowlist only (a
state file is data, not code).
Does not know: files, threads, clocks, the start decision (writer.py, store.py).
"""

from __future__ import annotations

import base64
import io
import pickle
from dataclasses import dataclass
from typing import Any

import numpy as np

from softplc.core import memory
from softplc.core.errors import SoftplcError
from softplc.core.events import EventMemory
from softplc.core.held import KEPT_AREAS, HeldOutputs
from softplc.core.image import AREAS, ProcessImage
from softplc.core.lifecycle import PlcState
from softplc.core.net import (
    Busy,
    CompiledNet,
    NetState,
    Token,
    persistent_places,
    places_marked,
)
from softplc.core.plc import Plc
from softplc.core.problems import FaultCode
from softplc.core.symbols import Retain, Symbol, persistent_memory
from softplc.core.values import record_problems, value_problem
from softplc.runtime.retain.store import SnapshotInvalid


class RetainValueError(SoftplcError, ValueError):
    """A token in the PLC's state holds a value the runtime cannot carry (core/values.py)."""


# -- capture (scan thread) and encoding (writer thread) ---------------------------------------

@dataclass(frozen=True, slots=True)
class Capture:
    """Copies taken at a scan boundary: consistent, cheap to take, encoded later."""

    net: CompiledNet
    state: PlcState
    fault_code: int
    scan_count: int
    now_ns: int
    net_state: NetState
    image: ProcessImage
    held: HeldOutputs | None  # the program's outputs kept at a stop or device fault
    stopped_at_ns: int | None
    events_last: dict[str, int | float]
    events_armed: dict[str, bool]
    field: dict[str, bytes]  # driver name -> pickled sim plant (simulation only)
    forces: tuple[tuple[str, int, int | None], ...] = ()  # (symbol, value, program's value)
    fault_reason: str = ""


def capture(plc: Plc, now_ns: int, plants: dict[str, object]) -> Capture | None:
    """The PLC after the scan at `now_ns`; None when there is no program to retain."""
    if plc.net is None or plc.engine is None:
        return None
    held = None if plc.held is None else plc.held.copy()
    net_state, image = plc.engine.state.copy(), plc.image.copy()
    # Paused at a breakpoint (docs/debug.md): the net as it will run on, whoever restores
    # it: its timers past the pause (the time rule), the program's outputs, not `safe`'s.
    if shift := plc.debug.frozen_shift(now_ns):
        net_state.enabled_since = {t: ns + shift for t, ns in net_state.enabled_since.items()}
        net_state.busy = {t: Busy(b.end_ns + shift, b.produce) for t, b in net_state.busy.items()}
    if plc.debug.held is not None:
        plc.debug.held.restore(image)
    return Capture(plc.net, plc.state, plc.fault_code, plc.scan_count, now_ns,
                   net_state, image, held, plc.stopped_at_ns,
                   dict(plc.events.last), dict(plc.events.armed),
                   {name: pickle.dumps(plant) for name, plant in plants.items()},
                   tuple(plc.forces.triples()), plc.fault_reason)


def encode(cap: Capture, seq: int, wall_ns: int) -> dict[str, Any]:
    net, st = cap.net, cap.net_state
    places, transitions = net.place_names, net.transitions
    return {
        "seq": seq, "written_unix_ns": wall_ns,
        "program": net.name, "program_hash": net.program_hash,
        "state": cap.state.name, "fault_code": int(cap.fault_code),
        "fault_reason": cap.fault_reason,
        "scan_count": cap.scan_count, "now_ns": cap.now_ns, "stopped_at_ns": cap.stopped_at_ns,
        "marking": {places[p]: int(n) for p, n in enumerate(st.marking)},
        "tokens": {places[p]: [_record(places[p], i, t) for i, t in enumerate(toks)]
                   for p, toks in st.tokens.items()},
        "enabled_since_ns": {transitions[t].name: ns for t, ns in st.enabled_since.items()},
        "busy": {transitions[t].name: {"end_ns": b.end_ns, "produce": [
            [places[p], n, None if r is None else _record(places[p], 0, r)]
            for p, n, r in b.produce]}
            for t, b in st.busy.items()},
        "image": {area: _pack(getattr(cap.image, area)) for area in AREAS},
        "held": None if cap.held is None else [_pack(cap.held.areas[a]) for a in KEPT_AREAS],
        "events": {"last": cap.events_last, "armed": cap.events_armed},
        "field_simulation_only": {name: base64.b64encode(blob).decode()
                                  for name, blob in cap.field.items()},
        "forces": [list(f) for f in cap.forces],  # kept across a warm restart
        # Which locations hold persistent variables: a cold start of another version takes
        # these back, and leaves a symbol the snapshot's program did not keep at its `init:`.
        "persistent_memory": [_variable(s) for s in persistent_memory(net.io)],
    }


def _variable(sym: Symbol) -> list[Any]:
    scale = sym.scaling
    return [str(sym.address), sym.type.value,
            None if scale is None else [list(scale.raw), list(scale.eng)]]


def _record(place: str, index: int, token: Any) -> dict[str, Any]:
    """A token as JSON can hold it, or RetainValueError naming it: never a TypeError from deep
    inside json (that once killed the writer thread for good)."""
    record = dict(token)
    for name, value in record.items():
        problem = value_problem(value)
        if problem is not None or not isinstance(name, str):
            raise RetainValueError(f"place {place}: token {index} field {name!r}: "
                                   f"{problem or 'field name is not text'}")
    return record


def _pack(values: np.ndarray) -> str:
    """An image area as base64 of its little-endian bytes: 5 k values in microseconds."""
    return base64.b64encode(values.astype(values.dtype.newbyteorder("<")).tobytes()).decode()


def _unpack(text: str, like: np.ndarray) -> np.ndarray:
    values = np.frombuffer(base64.b64decode(text), dtype=like.dtype.newbyteorder("<"))
    if values.shape != like.shape:
        raise SnapshotInvalid(f"image area of {values.size} values instead of {like.size}")
    return values.astype(like.dtype)


# -- restore ------------------------------------------------------------------------------

def restore(plc: Plc, payload: dict[str, Any], resume: bool) -> PlcState:
    """Put a snapshot into `plc`, which already holds the same program (downloaded, STOPPED).
    A snapshot taken while RUNNING resumes only if `resume`; otherwise it waits STOPPED with
    its timers frozen at the snapshot instant (`softplc resume` continues it)."""
    net, engine = plc.net, plc.engine
    assert net is not None and engine is not None and net.program_hash == payload["program_hash"]
    places, names = net.place_index, {t.name: t.index for t in net.transitions}
    state = NetState.initial(net)
    state.marking[:] = 0
    for name, count in payload["marking"].items():
        state.marking[places[name]] = count
    state.tokens = {places[name]: _tokens(name, toks) for name, toks in payload["tokens"].items()}
    state.enabled_since = {names[t]: ns for t, ns in payload["enabled_since_ns"].items()}
    state.busy = {names[t]: Busy(b["end_ns"], tuple((places[p], n, r) for p, n, r in b["produce"]))
                  for t, b in payload["busy"].items()}
    engine.state = state
    engine.invalidate()  # enabledness is recomputed from the restored marking
    for area in AREAS:  # a snapshot from before the 32/64-bit areas lacks them: zeros
        target = getattr(plc.image, area)
        target[:] = _unpack(payload["image"][area], target) if area in payload["image"] else 0
    plc.image.copy_into(plc.prev)
    plc.events = EventMemory(dict(payload["events"]["last"]), dict(payload["events"]["armed"]))
    plc.scan_count = payload["scan_count"]
    plc.fault_code = FaultCode(payload["fault_code"])
    plc.fault_reason = str(payload.get("fault_reason", ""))
    plc.forces.restore(net.io.symbols, [(str(n), int(v), s) for n, v, s in
                                        payload.get("forces", [])])
    was = PlcState[payload["state"]]
    plc.held = _held(payload["held"], plc.image)
    plc.stopped_at_ns = payload["stopped_at_ns"]
    plc.state = was
    _initial_unretained(plc)
    if was is PlcState.RUNNING and not resume:
        plc.state = PlcState.STOPPED
        plc.stopped_at_ns = payload["now_ns"]
        plc.held = HeldOutputs.of(plc.image)
    return plc.state


def _held(packed: list[str] | None, image: ProcessImage) -> HeldOutputs | None:
    """The kept outputs, area by area in KEPT_AREAS' order. A file from before %QD/%QL were
    kept holds %QX and %QW only: the others keep what the image holds (the safe values a
    stopped PLC drives), as a resume put them then."""
    if packed is None:
        return None
    held = HeldOutputs.of(image)
    for area, text in zip(KEPT_AREAS, packed, strict=False):
        held.areas[area][:] = _unpack(text, held.areas[area])
    return held


def _initial_unretained(plc: Plc) -> None:
    """What is declared `retain: none` starts anew at a warm start: its place with the
    initial marking, its memory symbol at its `init:` or 0 (docs/retain.md, retain per
    variable)."""
    net, engine = plc.net, plc.engine
    assert net is not None and engine is not None
    state = engine.state
    for p in places_marked(net, Retain.NONE):
        state.marking[p] = net.initial[p]
        if net.coloured[p]:
            state.tokens[p] = list(net.initial_tokens.get(p, ()))
    memory.unretained(plc.image, net.io)
    engine.invalidate()


def restore_persistent(plc: Plc, payload: dict[str, Any]) -> list[str]:
    """At a cold start: put in the persistent places and memory symbols of a snapshot of a
    program of the same name (`plc` holds the downloaded program, READY); returns their names.
    Places by name, memory symbols at their address in this program's io image, when the
    snapshot's program kept the same variable there (address, type, scale)."""
    net, engine = plc.net, plc.engine
    assert net is not None and engine is not None and net.name == payload["program"]
    kept = []
    for p in persistent_places(net):
        name = net.place_names[p]
        count = payload["marking"].get(name)
        if count is None or 0 <= net.capacity[p] < count or \
                bool(net.coloured[p]) != (name in payload["tokens"]):
            continue
        engine.state.marking[p] = count
        if net.coloured[p]:
            engine.state.tokens[p] = _tokens(name, payload["tokens"][name])
        kept.append(name)
    areas = {}
    kept_there = payload.get("persistent_memory")  # absent from files before `init:`
    for sym in persistent_memory(net.io):
        area, index = sym.address.attr, sym.address.index
        if area not in payload["image"] or (kept_there is not None
                                            and _variable(sym) not in kept_there):
            continue
        if area not in areas:
            areas[area] = _unpack(payload["image"][area], getattr(plc.image, area))
        getattr(plc.image, area)[index] = areas[area][index]
        kept.append(sym.name)
    engine.invalidate()
    return kept


def _tokens(place: str, records: list[Any]) -> list[Token]:
    """Restored records carry only token values (a file is data from outside)."""
    for i, record in enumerate(records):
        for _, problem in record_problems(record):
            raise SnapshotInvalid(f"place {place}: token {i}: {problem}")
    return [dict(r) for r in records]


class _PlantUnpickler(pickle.Unpickler):
    """Only plant models and what they are made of: a state file is data, not code."""

    ALLOWED: frozenset[tuple[str, str]] = frozenset({
        ("random", "Random"), ("builtins", "set"), ("builtins", "frozenset"),
        ("copyreg", "_reconstructor"), ("builtins", "object")})

    def find_class(self, module: str, name: str) -> Any:
        if module.startswith("softplc.devices.plants.") or (module, name) in self.ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"{module}.{name} is not a plant model")


def load_plant(blob: str) -> object:
    return _PlantUnpickler(io.BytesIO(base64.b64decode(blob))).load()
