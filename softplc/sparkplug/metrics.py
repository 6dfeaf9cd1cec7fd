"""What the edge node reports: the metrics of the running program's symbols and of the PLC,
their Sparkplug datatypes, aliases and properties, and report by exception.

Owns: the IEC type -> Sparkplug datatype table (docs/sparkplug.md), a scaled symbol as a
Double in engineering units with engUnit/engLow/engHigh properties, the `readOnly` property,
the node metrics (PLC/State, PLC/Program, PLC/Program Hash, PLC/Scan Count, PLC/Fault,
Node Control/Rebirth, Node Control/Command, Node Control/Command Status, bdSeq), the aliases
of one birth (1.. in birth order, Rebirth and bdSeq without), and which metrics changed
since the last report (a real moves more than the deadband).
Does not know: MQTT, the channel, the snapshot's transport.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

from softplc.core.datatypes import SymType
from softplc.core.image import AddressError, ProcessImage, parse_address
from softplc.core.present import scaling_of, sym_type, value
from softplc.security.writes import symbol_refusal
from softplc.sparkplug import codec
from softplc.sparkplug.codec import Metric, Value

DATATYPES: Final = {SymType.BOOL: codec.BOOLEAN, SymType.INT: codec.INT16,
                    SymType.WORD: codec.UINT16, SymType.DINT: codec.INT32,
                    SymType.UDINT: codec.UINT32, SymType.REAL: codec.FLOAT,
                    SymType.LREAL: codec.DOUBLE}
REBIRTH: Final = "Node Control/Rebirth"
COMMAND: Final = "Node Control/Command"  # start, stop, resume, reset (--sparkplug-commands)
STATUS: Final = "Node Control/Command Status"  # the outcome of the last NCMD/DCMD
BDSEQ: Final = "bdSeq"
# node metric -> (datatype, the status board key it shows)
NODE: Final = {"PLC/State": (codec.STRING, "state"), "PLC/Program": (codec.STRING, "program"),
               "PLC/Program Hash": (codec.STRING, "program_hash"),
               "PLC/Scan Count": (codec.UINT64, "scan_count"),
               "PLC/Fault": (codec.STRING, "fault_reason")}


@dataclass(frozen=True, slots=True)
class SymbolMetric:
    """One symbol of the status board as a metric."""

    name: str
    alias: int
    datatype: int
    type_name: str
    address: Any  # core.image.Address
    scale: Any
    refusal: str | None  # why no client may write it (security/writes.py), None: writable
    properties: tuple[tuple[str, int, Value], ...]

    @property
    def writable(self) -> bool:
        return self.refusal is None

    def read(self, image: ProcessImage) -> Value:
        number = value(self.type_name, image.get(self.address), self.scale)
        return float(number) if self.datatype in (codec.FLOAT, codec.DOUBLE) else number


def symbol_metrics(document: Mapping[str, Any], first_alias: int) -> list[SymbolMetric]:
    """The board's symbols (sorted by name) whose type this version knows, aliases from
    `first_alias`."""
    found: list[SymbolMetric] = []
    symbols = document.get("symbols") or {}
    for name in sorted(symbols):
        entry = symbols[name]
        t = sym_type(entry.get("type")) if isinstance(entry, dict) else None
        if t is None:
            continue
        try:
            address = parse_address(str(entry.get("address")))
        except AddressError:
            continue
        scale = scaling_of(entry.get("scale"), entry.get("type"))
        datatype = codec.DOUBLE if scale is not None and t is not SymType.BOOL else DATATYPES[t]
        refusal = symbol_refusal(str(name), entry)
        props: list[tuple[str, int, Value]] = [("readOnly", codec.BOOLEAN, refusal is not None)]
        if scale is not None and t is not SymType.BOOL:
            props += [("engUnit", codec.STRING, scale.unit),
                      ("engLow", codec.DOUBLE, float(min(scale.eng))),
                      ("engHigh", codec.DOUBLE, float(max(scale.eng)))]
        found.append(SymbolMetric(str(name), first_alias + len(found), datatype,
                                  str(entry.get("type")), address, entry.get("scale"),
                                  refusal, tuple(props)))
    return found


class Report:
    """The metrics of one birth and what was last sent of each (report by exception)."""

    def __init__(self, document: Mapping[str, Any], deadband: float) -> None:
        self.document = document
        self.deadband = deadband
        self.node_alias = {name: i + 1 for i, name in enumerate([*NODE, COMMAND, STATUS])}
        self.symbols = symbol_metrics(document, len(self.node_alias) + 1)
        self.by_name = {m.name: m for m in self.symbols}
        self.by_alias = {m.alias: m for m in self.symbols}
        self.sent: dict[int, Value] = {}  # alias -> the value last reported
        self.status: str = ""

    def node_values(self, status: Mapping[str, Any]) -> dict[str, Value]:
        out: dict[str, Value] = {}
        for name, (datatype, key) in NODE.items():
            raw = status.get(key)
            out[name] = int(raw or 0) if datatype == codec.UINT64 else \
                ("" if raw is None else str(raw))
        out[COMMAND] = ""
        out[STATUS] = self.status
        return out

    def current(self, status: Mapping[str, Any], image: ProcessImage | None
                ) -> dict[int, tuple[int, Value]]:
        """alias -> (datatype, value) of every aliased metric now."""
        out: dict[int, tuple[int, Value]] = {}
        for name, number in self.node_values(status).items():
            datatype = NODE[name][0] if name in NODE else codec.STRING
            out[self.node_alias[name]] = (datatype, number)
        for metric in self.symbols:
            out[metric.alias] = (metric.datatype,
                                 metric.read(image) if image is not None else None)
        return out

    def birth(self, status: Mapping[str, Any], image: ProcessImage | None, bdseq: int,
              now_ms: int) -> list[Metric]:
        """Every metric with name, alias, datatype, value and timestamp (spec 5.16)."""
        now = self.current(status, image)
        self.sent = {alias: v for alias, (_, v) in now.items()}
        names = {alias: name for name, alias in self.node_alias.items()}
        metrics = [Metric(BDSEQ, codec.INT64, bdseq, timestamp=now_ms),
                   Metric(REBIRTH, codec.BOOLEAN, False, timestamp=now_ms)]
        for alias, (datatype, number) in now.items():
            symbol = self.by_alias.get(alias)
            metrics.append(Metric(symbol.name if symbol else names[alias], datatype, number,
                                  alias, now_ms, symbol.properties if symbol else ()))
        return metrics

    def changes(self, status: Mapping[str, Any], image: ProcessImage | None, now_ms: int
                ) -> list[Metric]:
        """The metrics that changed since they were last sent, by alias only (no name, no
        datatype: spec 6.4.6), now counted as sent."""
        out: list[Metric] = []
        for alias, (datatype, number) in self.current(status, image).items():
            if alias in self.sent and not self._moved(datatype, self.sent[alias], number):
                continue
            self.sent[alias] = number
            out.append(Metric(None, datatype, number, alias, now_ms, typed=False))
        return out

    def _moved(self, datatype: int, before: Value, now: Value) -> bool:
        if datatype in (codec.FLOAT, codec.DOUBLE) and isinstance(before, float) \
                and isinstance(now, float):
            if math.isnan(before) or math.isnan(now):
                return math.isnan(before) != math.isnan(now)
            return abs(now - before) > self.deadband or (self.deadband == 0 and now != before)
        return before != now
