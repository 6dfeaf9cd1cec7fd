"""The recent past's rings (softplc/api/historyring.py) and sampler (history.py), in process:
bounded in scans and bytes, gaps named, values typed, the marking the window starts with,
fired transitions per board sample, a new program or a restarted PLC starting anew."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from softplc.api.history import Sampler
from softplc.api.historyring import MAX_BYTES, MAX_SCANS, History, Layout, gaps
from softplc.core.image import ImageSizes, ProcessImage, parse_address
from softplc.core.lifecycle import PlcState
from softplc.core.snapshot import Snapshot, SnapshotUnavailable, Status

SYMBOLS = {"run_i": ("%IX0.0", "bool"), "small": ("%MW0", "int"), "temp": ("%MD0", "real"),
           "level": ("%ML0", "lreal"),
           "pct": ("%QW1", "int", {"raw": [0, 27648], "eng": [0.0, 100.0], "unit": "%"})}


def board(scan: int = 0, program_hash: str = "h1", marking: dict[str, int] | None = None,
          fired: dict[str, int] | None = None, symbols: dict[str, Any] = SYMBOLS,
          places: tuple[str, ...] = ("idle", "busy")) -> dict[str, Any]:
    return {"program": "p", "program_hash": program_hash, "scan_count": scan,
            "marking": marking or {}, "forced": {},
            "symbols": {n: {"address": s[0], "type": s[1],
                            **({"scale": s[2]} if len(s) > 2 else {})}
                        for n, s in symbols.items()},
            "net": {"nodes": {"places": [{"name": p} for p in places],
                              "transitions": [{"name": "go"}, {"name": "back"}]}},
            "net_live": {"fired_counts": fired or {}}}


def image(**raw: int) -> ProcessImage:
    img = ProcessImage(ImageSizes())
    for name, value in raw.items():
        img.set(parse_address(str(SYMBOLS[name][0])), value)
    return img


def fill(history: History, scans: range | list[int], img: ProcessImage | None = None) -> None:
    for scan in scans:
        history.add_scan(scan, scan * 10_000_000, int(PlcState.RUNNING), 0, img or image())


def test_the_rings_keep_the_last_max_scans() -> None:
    layout = Layout.of_board(board())
    assert layout is not None
    history = History(layout)
    fill(history, range(1, 2501))
    window = history.window(-1, ["small"], ["idle"], 0)
    assert window["scans"] == list(range(1501, 2501)) and len(window["scans"]) == MAX_SCANS
    assert window["oldest_scan"] == 1501 and window["gaps"] == []
    assert window["t_ms"][-1] == 25_000.0 and window["state"][-1] == "RUNNING"
    assert history.window(2490, [], [], 0)["scans"] == list(range(2491, 2501))  # since


def test_the_bytes_bound_wins_for_a_large_image() -> None:
    many = {f"w{i}": (f"%MW{i}", "word") for i in range(1000)}
    many |= {f"b{i}": (f"%MX{i // 8}.{i % 8}", "bool") for i in range(800)}
    layout = Layout.of_board(board(symbols=many, places=tuple(f"p{i}" for i in range(3000))))
    assert layout is not None
    history = History(layout)
    scans, samples = history.max_rows
    assert scans == (MAX_BYTES // 2) // (8 * (1800 + 4)) < MAX_SCANS
    assert samples == (MAX_BYTES // 2) // (8 * (3000 + 2 + 2)) < MAX_SCANS
    assert history.nbytes <= MAX_BYTES
    fill(history, range(3 * scans))
    assert len(history.window(-1, ["w0"], [], 0)["scans"]) == scans
    assert history.nbytes <= MAX_BYTES


def test_gaps_name_the_scans_not_sampled() -> None:
    assert gaps(np.array([1, 2, 3, 7, 8, 12])) == [[4, 6], [9, 11]]
    layout = Layout.of_board(board())
    assert layout is not None
    history = History(layout)
    fill(history, [5, 6, 9, 10])
    assert history.window(-1, [], [], 0)["gaps"] == [[7, 8]]


def test_values_are_typed_as_their_symbols_read() -> None:
    layout = Layout.of_board(board())
    assert layout is not None
    history = History(layout)
    temp = int(np.float32(12.5).view(np.uint32))
    level = int(np.float64(-1e300).view(np.uint64))
    fill(history, [1], image(run_i=1, small=0xFFFD, temp=temp, level=level, pct=13824))
    values = history.window(-1, list(SYMBOLS), [], 0)["values"]
    assert values == {"run_i": [True], "small": [-3], "temp": [12.5], "level": [-1e300],
                      "pct": [50.0]}


def test_board_samples_carry_marking_fired_and_the_window_start() -> None:
    layout = Layout.of_board(board())
    assert layout is not None
    history = History(layout)
    fill(history, range(1, 31))
    history.add_board(5, 50, {"idle": 1}, {}, {})
    history.add_board(10, 100, {"busy": 1}, {"go": 1}, {"run_i": 1})
    history.add_board(10, 100, {"busy": 1}, {"go": 1}, {"run_i": 1})  # the same: once
    history.add_board(15, 150, {"idle": 1}, {"go": 1, "back": 1}, {})
    history.add_board(20, 200, {"idle": 1}, {}, {})  # counts reset: unknown
    b = history.window(-1, [], ["idle", "busy"], 0)["board"]
    assert b["scans"] == [5, 10, 15, 20]
    assert b["marking"] == {"idle": [1, 0, 1, 1], "busy": [0, 1, 0, 0]}
    assert b["fired"] == [None, {"go": 1}, {"back": 1}, None]
    assert b["forced"] == [{}, {"run_i": 1}, {}, {}]
    # since 12: the sample at 10 says what the marking was at 13 only if asked from there
    assert history.window(12, [], ["busy"], 0)["board"]["scans"] == [15, 20]
    fill(history, range(31, 1020))  # scan 5..19 leave the scan ring: the window starts at
    assert history.window(-1, [], ["idle"], 0)["board"]["scans"] == [20]  # its last sample


class Source:
    def __init__(self) -> None:
        self.status = Status(PlcState.RUNNING, 1, program_hash="h1", period_us=10_000,
                             published_ns=10_000_000)
        self.doc = board(1)
        self.img = image(small=7)

    def latest(self) -> Snapshot:
        if self.status.scan_count < 0:
            raise SnapshotUnavailable("none")
        return Snapshot(1, self.img, self.status)

    def read(self) -> dict[str, Any]:
        return self.doc


def test_the_sampler_follows_program_and_restarts() -> None:
    source = Source()
    sampler = Sampler(source, source, max_scans=100)
    due = sampler.step(10_500_000)
    assert due == 10_000_000 + 12_500_000  # a quarter period after the next publish
    assert sampler.history is not None and sampler.history.last_scan() == 1
    for scan in (2, 3, 5):
        source.status = replace(source.status, scan_count=scan, published_ns=scan * 10_000_000)
        sampler.step(scan * 10_000_000 + 1000)
    window = sampler.history.window(-1, ["small"], ["idle"], 0)
    assert window["scans"] == [1, 2, 3, 5] and window["gaps"] == [[4, 4]]
    assert window["values"]["small"] == [7, 7, 7, 7]
    source.status = replace(source.status, scan_count=1)  # the PLC started again
    sampler.step(60_000_000)
    assert sampler.history.window(-1, [], [], 0)["scans"] == [1]
    source.status = replace(source.status, scan_count=2, program_hash="h2")  # a download:
    sampler.step(70_000_000)  # the board still shows h1: no history of h2 yet
    assert sampler.history.layout.program_hash == "h1"
    source.doc = board(2, program_hash="h2")
    sampler.step(80_000_000)
    assert sampler.history.layout.program_hash == "h2" and sampler.history.last_scan() == 2
    source.status = replace(source.status, scan_count=-1)
    assert sampler.step(90_000_000) == 90_000_000 + 50_000_000  # nothing to read: idle


def test_no_history_when_turned_off() -> None:
    source = Source()
    sampler = Sampler(source, source, max_scans=0)
    sampler.start()  # no thread
    sampler.stop()
    assert sampler.history is None

