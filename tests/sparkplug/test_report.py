"""Report by exception without a broker: which metrics an NDATA carries (changed ones only, by
alias, a real only past the deadband, NaN once), and the birth's metric table (types from the
status board's entries, engineering properties of a scaled symbol, readOnly)."""

from __future__ import annotations

import math
from typing import Any

from softplc.core.datatypes import SymType, raw_of
from softplc.core.image import ProcessImage, parse_address
from softplc.sparkplug import codec
from softplc.sparkplug.metrics import Report

BOARD: dict[str, Any] = {
    "state": "RUNNING", "program": "p", "program_hash": "ab", "scan_count": 1,
    "symbols": {
        "flow": {"address": "%MD0", "type": "real", "direction": "memory"},
        "count": {"address": "%MW0", "type": "int", "direction": "memory",
                  "hmi_writable": False},
        "temp": {"address": "%IW0", "type": "int", "direction": "in",
                 "scale": {"raw": [-500, 1500], "eng": [-50.0, 150.0], "unit": "°C"}},
        "future": {"address": "%MW1", "type": "int128"},  # a type this version lacks
    }}


def _image(flow: float, count: int, temp_raw: int) -> ProcessImage:
    image = ProcessImage()
    image.set(parse_address("%MD0"), raw_of(SymType.REAL, flow))
    image.set(parse_address("%MW0"), raw_of(SymType.INT, count))
    image.set(parse_address("%IW0"), raw_of(SymType.INT, temp_raw))
    return image


def _changed(report: Report, image: ProcessImage) -> dict[str, Any]:
    names = {m.alias: m.name for m in report.symbols}
    return {names.get(m.alias, m.alias): m.value for m in report.changes(BOARD, image, 2)}


def test_the_birth_table() -> None:
    report = Report(BOARD, deadband=0.0)
    birth = {m.name: m for m in report.birth(BOARD, _image(1.5, -3, 200), 7, 1)}
    assert birth["bdSeq"].value == 7 and birth["bdSeq"].datatype == codec.INT64
    assert (birth["flow"].datatype, birth["flow"].value) == (codec.FLOAT, 1.5)
    assert (birth["count"].datatype, birth["count"].value) == (codec.INT16, -3)
    assert birth["temp"].datatype == codec.DOUBLE and birth["temp"].value == 20.0
    assert dict((k, v) for k, _, v in birth["temp"].properties) == {
        "readOnly": True, "engUnit": "°C", "engLow": -50.0, "engHigh": 150.0}
    assert dict((k, v) for k, _, v in birth["count"].properties) == {"readOnly": True}
    assert dict((k, v) for k, _, v in birth["flow"].properties) == {"readOnly": False}
    assert "future" not in birth
    assert all(m.timestamp == 1 for m in birth.values())


def test_only_changes_past_the_deadband_are_reported() -> None:
    report = Report(BOARD, deadband=0.5)
    report.birth(BOARD, _image(1.0, 0, 0), 0, 1)
    assert _changed(report, _image(1.0, 0, 0)) == {}
    assert _changed(report, _image(1.4, 0, 0)) == {}  # within the deadband of 1.0
    assert _changed(report, _image(1.6, 0, 0)) == {"flow": 1.6}  # the real as the program reads it
    assert _changed(report, _image(1.6, 1, 4)) == {"count": 1}  # temp 0.4 °C: within
    assert _changed(report, _image(1.6, 1, 10)) == {"temp": 1.0}  # 1.0 °C from 0.0: past
    metrics = report.changes(BOARD, _image(math.nan, 1, 10), 3)
    assert len(metrics) == 1 and math.isnan(float(metrics[0].value or 0))
    assert metrics[0].name is None and not metrics[0].typed
    assert report.changes(BOARD, _image(math.nan, 1, 10), 4) == []  # NaN again: no change
    report.status = "#1 write flow: queued"
    assert [m.value for m in report.changes(BOARD, _image(math.nan, 1, 10), 5)] == [
        "#1 write flow: queued"]
