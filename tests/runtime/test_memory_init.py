"""Initial values of memory symbols (`init:`, issue 30; docs/retain.md, retain per variable).

In process on a virtual clock: what a cold start puts in (typed, scaled, bool), what a warm
start keeps (retained, persistent) and puts back (`retain: none`), what a download of another
version, a reset and an online change keep or set, the persistent values of a cold start of
another version, and the same values in `simulate` and `replay`, bit for bit.
"""

from __future__ import annotations

import struct
from pathlib import Path

from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.present import shown
from softplc.core.scan import scan
from softplc.core.symbols import Symbol
from softplc.debug.replay import replay
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop
from softplc.runtime.offline.simulate import simulate

MS = 1_000_000
IO = """
symbols:
  lamp:     {address: '%QX0.0', safe: false}
  scratch:  {address: '%MW0', retain: none, init: 7}
  setpoint: {address: '%MW1', init: 50}
  total:    {address: '%MD0', type: dint, retain: persistent, init: -100}
  level_sp: {address: '%MW2', type: int, init: 75,
             scale: {raw: [0, 27648], eng: [0.0, 100.0], unit: '%'}}
  ratio:    {address: '%MD1', type: real, init: 0.1}
  armed:    {address: '%MX0.0', init: true}
  plain:    {address: '%MW3'}
"""
# `count` fires while `src` has tokens: the persistent total counts, the scratch word too.
PROGRAM = """program: counts
io_image: io.yaml
places:
  src: {tokens: 3}
  counted: {outputs: [lamp]}
transitions:
  count: {from: [src], to: [counted], when: armed,
          do: ["total = total + 1", "scratch = scratch + 1"]}
"""
INITIAL = {"scratch": 7, "setpoint": 50, "total": -100, "level_sp": 75.0, "ratio": 0.1,
           "armed": True, "plain": 0}
LEVEL_RAW = 20736  # 75 % of 27648


def write(directory: Path, body: str = PROGRAM, io: str = IO, name: str = "counts.yaml") -> str:
    (directory / "io.yaml").write_text(io, encoding="utf-8")
    path = directory / name
    path.write_text(body, encoding="utf-8")
    return str(path)


def values(plc: Plc) -> dict[str, object]:
    assert plc.net is not None
    return {name: value_of(plc, sym) for name, sym in plc.net.io.symbols.items()
            if sym.direction.value == "memory"}


def value_of(plc: Plc, sym: Symbol) -> object:
    return shown(sym.type.value, plc.image.get(sym.address), sym.scaling)


def loop(program: str, state: Path, scans: int, clock_ns: int = 0,
         policy: str = "warm") -> ScanLoop:
    config = LoopConfig(program=program, start=True, period_ns=10 * MS, max_scans=scans,
                        state_dir=str(state), boot_policy=policy)
    return ScanLoop(config, None, None, VirtualClock(clock_ns))


def run_by_hand(scan_loop: ScanLoop, scans: int) -> None:
    """Scans on the loop's virtual clock, without the shutdown that `run()` ends with."""
    clock = scan_loop.clock
    assert isinstance(clock, VirtualClock)
    for _ in range(scans):
        scan_loop.scan_once(clock.now_ns())
        clock.advance(10 * MS)


def test_a_cold_start_puts_each_init_value_in_its_type_and_scale(tmp_path: Path) -> None:
    first = loop(write(tmp_path), tmp_path / "state", scans=1)
    assert first.start_mode == "cold"
    first.run()  # the download is applied in the first scan; `count` fires in it too
    plc = first.runner.plc
    assert values(plc) == {**INITIAL, "scratch": 8, "total": -99}
    assert plc.image.mw[2] == LEVEL_RAW  # a scaled init is stored as its raw count
    assert plc.image.md[1] == struct.unpack("<I", struct.pack("<f", 0.1))[0]  # a real's bits
    assert plc.image.md[0] == (-99) & 0xFFFFFFFF  # a dint's two's complement


def test_a_warm_start_keeps_retained_values_and_puts_non_retained_back_to_init(
        tmp_path: Path) -> None:
    program, state = write(tmp_path), tmp_path / "state"
    first = loop(program, state, scans=10)
    run_by_hand(first, scans=10)
    plc = first.runner.plc
    assert values(plc)["total"] == -97 and values(plc)["scratch"] == 10
    plc.image.mw[1], plc.image.mw[2], plc.image.mw[3] = 60, 13824, 9  # as HMI writes leave them
    first.shutdown()  # the final snapshot holds them
    warm = loop(program, state, scans=20, clock_ns=10**12)
    assert warm.start_mode == "warm", warm.start_reason
    assert warm.runner.plc.state is PlcState.RUNNING
    assert values(warm.runner.plc) == {**INITIAL, "scratch": 7, "total": -97, "setpoint": 60,
                                       "level_sp": 50.0, "plain": 9}


def test_reset_and_a_download_of_another_version_put_only_non_retained_symbols_back(
        tmp_path: Path) -> None:
    v1 = compile_file(write(tmp_path))
    v2 = compile_file(write(tmp_path, PROGRAM.replace("src: {tokens: 3}", "src: {tokens: 2}"),
                            name="counts2.yaml"))
    plc, now = Plc.empty(), 0
    for command in (ProgramCommand(Command.DOWNLOAD, v1), ProgramCommand(Command.START)):
        plc.apply(command, now)
    for _ in range(2):
        now += 10 * MS
        scan(plc, plc.image.copy(), now)
    plc.image.mw[1] = 60  # an operator's setpoint
    assert values(plc) == {**INITIAL, "scratch": 9, "total": -98, "setpoint": 60}
    plc.apply(ProgramCommand(Command.STOP), now)
    plc.apply(ProgramCommand(Command.RESET), now)
    assert values(plc) == {**INITIAL, "total": -98, "setpoint": 60}
    plc.apply(ProgramCommand(Command.START), now)
    now += 10 * MS
    scan(plc, plc.image.copy(), now)
    plc.apply(ProgramCommand(Command.STOP), now)
    plc.apply(ProgramCommand(Command.DOWNLOAD, v2), now)  # the persistent total is not init
    assert values(plc) == {**INITIAL, "total": -97, "setpoint": 60}


def test_a_symbol_new_to_the_image_takes_its_init_and_the_others_keep_their_values(
        tmp_path: Path) -> None:
    """A download or an online change keeps every variable both programs declare (the same
    address, type and scale); what is new (or now another type) starts at its init."""
    v1 = compile_file(write(tmp_path))
    io2 = (IO.replace("plain:    {address: '%MW3'}", "plain:    {address: '%MW3', init: 4}")
           .replace("setpoint: {address: '%MW1', init: 50}",
                    "setpoint: {address: '%MW1', type: int, init: -5}")
           + "  fresh:    {address: '%MW4', init: 321}\n")
    (tmp_path / "v2").mkdir()
    v2 = compile_file(write(tmp_path / "v2", io=io2))
    plc, now = Plc.empty(), 0
    for command in (ProgramCommand(Command.DOWNLOAD, v1), ProgramCommand(Command.START)):
        plc.apply(command, now)
    now += 10 * MS
    scan(plc, plc.image.copy(), now)
    plc.image.mw[3] = 9
    reply = plc.apply(ProgramCommand(Command.DOWNLOAD, v2, online=True), now)
    assert reply.startswith("online change"), reply
    # %MW3 was declared as the same word (only its init is new): its value stays; %MW1 is
    # an int now, another variable: its init; %MW4 is new
    assert values(plc) == {**INITIAL, "scratch": 8, "total": -99, "plain": 9,
                           "setpoint": -5, "fresh": 321}


def test_a_cold_start_of_another_version_keeps_persistent_values_and_inits_new_ones(
        tmp_path: Path) -> None:
    program, state = write(tmp_path), tmp_path / "state"
    first = loop(program, state, scans=10)
    run_by_hand(first, scans=10)
    first.runner.plc.image.mw[5] = 1234  # a location no symbol of this version declares
    first.shutdown()
    io2 = IO + "  batch:    {address: '%MW5', retain: persistent, init: 1}\n"
    (tmp_path / "v2").mkdir()
    v2 = write(tmp_path / "v2", PROGRAM.replace("src: {tokens: 3}", "src: {tokens: 1}"), io2)
    cold = loop(v2, state, scans=1, clock_ns=10**12)
    assert cold.start_mode == "cold" and "persistent kept" in cold.start_reason
    assert "total" in cold.start_reason and "batch" not in cold.start_reason
    # total from the snapshot, not its init; batch was not a persistent variable there: init
    assert values(cold.runner.plc) == {**INITIAL, "total": -97, "batch": 1}


def test_simulate_and_replay_start_from_the_same_init_values_bit_for_bit(
        tmp_path: Path) -> None:
    net = compile_file(write(tmp_path))
    trace = tmp_path / "trace.jsonl"
    report = simulate(net, 100 * MS, trace_path=trace)
    assert report["outputs_final"] == {"lamp": 1, **INITIAL, "armed": 1, "scratch": 10,
                                       "total": -97}
    again = simulate(net, 100 * MS)
    assert again["trace_sha256"] == report["trace_sha256"]
    result = replay(trace, net)
    assert result.ok and result.scans == 10, result.divergence
    # without the inits the same program runs differently: the trace is of these values
    plain = IO.replace("init: true", "init: false")
    (tmp_path / "other").mkdir()
    other = compile_file(write(tmp_path / "other", io=plain))
    assert simulate(other, 100 * MS)["trace_sha256"] != report["trace_sha256"]
