"""Watchdog: a scan that runs past period x watchdog faults the PLC, with safe outputs written
through the drivers before the next scan. The real ScanLoop on the real clock, bounded by
max_scans; the slow scans are many times the budget so that a loaded machine cannot make a
normal scan look slow or a slow one look normal. Sensitivity 1 here (the first scan over budget
faults); the default sensitivity and the hard limit: test_watchdog_sensitivity.py."""

from __future__ import annotations

import time
from pathlib import Path

from softplc.core.image import ProcessImage
from softplc.core.lifecycle import PlcState
from softplc.core.plc import FAULT_WATCHDOG
from softplc.devices.driver import Health
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.trace import read_trace

S = PlcState

IO = """\
symbols:
  w:    {address: "%IW0", driver: none, description: "a count the driver changes every scan"}
  lamp: {address: "%QX0.0", safe: false, driver: none}
  vent: {address: "%QX0.1", safe: true, driver: none}
"""

LAMP = """\
program: lamp
io_image: io.yaml
places:
  on: {tokens: 1, outputs: [lamp]}
"""

# A binding explosion: 32 x 32 token pairs (the search stops at 1000) for a guard that is never
# true and reads `w`, which changes every scan, so every scan searches again.
TOKENS = "[" + ", ".join(f"{{v: {i}}}" for i in range(32)) + "]"
GUARD = " or ".join(f"(a.v * {i + 3} + b.v * {i + 5} + w) % {97 + i} == 1000" for i in range(3))
PATHOLOGICAL = f"""\
program: explosion
io_image: io.yaml
places:
  on: {{tokens: 1, outputs: [lamp]}}
  left: {{tokens: {TOKENS}}}
  right: {{tokens: {TOKENS}}}
transitions:
  match:
    from: [{{place: left, var: a}}, {{place: right, var: b}}, on]
    to: [left, right, on]
    when: "{GUARD}"
"""


class SlowDriver:
    """A driver whose device answers in no time, except on read number `slow_read` (1-based),
    which takes `delay_s`. Logs every write as (reads so far, lamp, vent)."""

    name = "slow"

    def __init__(self, slow_read: int | None = None, delay_s: float = 0.0) -> None:
        self.slow_read, self.delay_s = slow_read, delay_s
        self.reads = 0
        self.writes: list[tuple[int, bool, bool]] = []

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def read_inputs(self, image: ProcessImage, now_ns: int) -> None:
        self.reads += 1
        image.iw[0] = self.reads
        if self.reads == self.slow_read:
            time.sleep(self.delay_s)

    def write_outputs(self, image: ProcessImage, now_ns: int) -> None:
        self.writes.append((self.reads, bool(image.qx[0]), bool(image.qx[1])))

    def health(self) -> Health:
        return Health.OK


def run_loop(tmp_path: Path, program: str, driver: SlowDriver, period_ns: int,
             watchdog: float, scans: int) -> tuple[ScanLoop, list[tuple[int, str]]]:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "prog.yaml").write_text(program, encoding="utf-8")
    trace = tmp_path / "trace.jsonl"
    config = LoopConfig(program=str(tmp_path / "prog.yaml"), start=True, period_ns=period_ns,
                        watchdog=watchdog, watchdog_sensitivity=1, max_scans=scans,
                        trace=str(trace))
    loop = ScanLoop(config, None, None)
    loop.runner.set_drivers([driver])  # the io image declares none: the loop keeps this one
    loop.run()
    return loop, [(r["k"], r["state"]) for r in read_trace(trace)]


def safe_writes_from(driver: SlowDriver) -> int:
    """Reads done when the first safe output image (lamp off, vent on) went to the driver."""
    return next(reads for reads, lamp, vent in driver.writes if (lamp, vent) == (False, True))


def test_a_slow_driver_faults_the_plc_before_the_next_scan(tmp_path: Path) -> None:
    period_ns, watchdog = 10_000_000, 20.0  # budget 200 ms
    driver = SlowDriver(slow_read=11, delay_s=50 * period_ns / 1e9)  # 500 ms in scan 10
    loop, states = run_loop(tmp_path, LAMP, driver, period_ns, watchdog, scans=16)
    plc = loop.runner.plc
    assert (plc.state, plc.fault_code) == (S.FAULTED, FAULT_WATCHDOG)
    assert states[:11] == [(k, "RUNNING") for k in range(11)]
    assert states[11:] == [(k, "FAULTED") for k in range(11, 16)]
    # Scan 10 wrote the program's outputs, then the watchdog wrote the safe ones at once.
    assert [w for w in driver.writes if w[0] == 11] == [(11, True, False), (11, False, True)]
    assert safe_writes_from(driver) == 11
    assert all((lamp, vent) == (False, True) for reads, lamp, vent in driver.writes if reads > 11)


def test_a_pathological_net_faults_the_plc_at_its_first_watched_scan(tmp_path: Path) -> None:
    period_ns, watchdog = 1_000_000, 10.0  # budget 10 ms; one round takes about 75 ms here
    driver = SlowDriver()
    loop, states = run_loop(tmp_path, PATHOLOGICAL, driver, period_ns, watchdog, scans=6)
    plc = loop.runner.plc
    assert (plc.state, plc.fault_code) == (S.FAULTED, FAULT_WATCHDOG)
    # Scan 0 downloads and starts (exempt: compiling is not execution); scan 1 is the first
    # the watchdog judges, and the first record after it is FAULTED.
    assert states == [(0, "RUNNING"), (1, "RUNNING")] + [(k, "FAULTED") for k in range(2, 6)]
    assert safe_writes_from(driver) == 2  # after scan 1's own write, before scan 2's read
    assert driver.writes[1] == (2, True, False)
    assert loop.stats.overruns >= 1
