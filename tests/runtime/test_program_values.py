"""A program's own values (issue 39, deliver 3; docs/retain.md, retain per variable).

The mixer (tests/runtime/mixer/) keeps the last batch's water temperature at %MD3, where the
shipped tank keeps its freeze-interlock setpoint `min_temp` (`init: 2.0`). A download of the
tank after the mixer, online or stopped, must start `min_temp` at 2.0, not at the mixer's
-50.0; the one variable both declare alike (`batches`: name, address, type) keeps its value,
and the reply and the status document name it. In process, on a virtual clock.
"""

from __future__ import annotations

import struct
from pathlib import Path

from softplc.core.image import ProcessImage
from softplc.core.lifecycle import Command, PlcState
from softplc.core.plc import Plc, ProgramCommand
from softplc.core.present import shown
from softplc.core.scan import scan
from softplc.program.compiler import compile_file
from softplc.runtime.clock import VirtualClock
from softplc.runtime.loop import LoopConfig, ScanLoop

MS = 1_000_000
HERE = Path(__file__).parent
MIXER = str(HERE / "mixer" / "mixer.yaml")
TANK = str(HERE.parent.parent / "programs" / "tank.yaml")


def real(plc: Plc, name: str) -> object:
    assert plc.net is not None
    sym = plc.net.io.symbols[name]
    return shown(sym.type.value, plc.image.get(sym.address), sym.scaling)


def mixed_one_batch() -> tuple[Plc, int]:
    """The mixer ran a batch with water at -50.0 °C: its last_temp (%MD3) holds -50.0."""
    mixer = compile_file(MIXER)
    plc, now = Plc.empty(), 0
    for command in (ProgramCommand(Command.DOWNLOAD, mixer), ProgramCommand(Command.START)):
        plc.apply(command, now)
    inputs = ProcessImage(plc.image.sizes)
    inputs.ix[1], inputs.iw[1] = True, -500 & 0xFFFF  # start; -50.0 °C (raw tenths)
    for level in (0, 27648, 27648, 0):  # dosing, dosed (last_temp written), ...
        inputs.iw[0] = level
        now += 10 * MS
        scan(plc, inputs, now)
    assert real(plc, "last_temp") == -50.0
    plc.image.md[0] = 7  # seven batches counted
    return plc, now


def test_an_online_download_of_another_program_starts_from_its_own_init_values() -> None:
    plc, now = mixed_one_batch()
    reply = plc.apply(ProgramCommand(Command.DOWNLOAD, compile_file(TANK), online=True,
                                     replace=True), now)
    assert reply.startswith("online replacement"), reply
    assert real(plc, "min_temp") == 2.0  # its init, not the mixer's last_temp (-50.0)
    assert real(plc, "fill_to") == 80.0  # its init, not the mixer's dose_to (60.0)
    assert real(plc, "batches") == 7  # declared alike in both: kept, and said
    assert reply.endswith("; kept values from mixer: batches"), reply
    assert plc.kept_across is not None and plc.kept_across.as_dict() == {
        "from": "mixer", "symbols": ["batches"]}


def test_a_stopped_download_of_another_program_starts_from_its_own_init_values() -> None:
    plc, now = mixed_one_batch()
    plc.apply(ProgramCommand(Command.STOP), now)
    reply = plc.apply(ProgramCommand(Command.DOWNLOAD, compile_file(TANK)), now)
    assert reply == "download: now STOPPED; kept values from mixer: batches", reply
    assert (real(plc, "min_temp"), real(plc, "fill_to"), real(plc, "batches")) == (2.0, 80.0, 7)
    assert real(plc, "last_level") == 0.0  # no init, another program: 0, not %MD1's bits


def test_another_version_keeps_its_values_and_says_nothing_kept_across() -> None:
    tank = compile_file(TANK)
    plc, now = Plc.empty(), 0
    for command in (ProgramCommand(Command.DOWNLOAD, tank), ProgramCommand(Command.START)):
        plc.apply(command, now)
    plc.image.md[3] = struct.unpack("<I", struct.pack("<f", -5.0))[0]  # an operator's value
    reply = plc.apply(ProgramCommand(Command.DOWNLOAD, compile_file(TANK), online=True), now)
    assert reply.startswith("online change"), reply
    assert real(plc, "min_temp") == -5.0 and plc.kept_across is None


def test_the_status_document_names_the_values_kept_from_the_mixer() -> None:
    loop = ScanLoop(LoopConfig(program=MIXER, start=True, period_ns=10 * MS, max_scans=5),
                    None, None, VirtualClock())
    loop.run()
    plc = loop.runner.plc
    plc.image.md[3] = struct.unpack("<I", struct.pack("<f", -50.0))[0]
    plc.image.md[0] = 3
    loop.pending.append(ProgramCommand(Command.DOWNLOAD, compile_file(TANK), online=True,
                                       replace=True, id=1))
    loop.config = LoopConfig(program=None, period_ns=10 * MS, max_scans=10)
    loop.run()
    assert plc.state is PlcState.RUNNING and plc.net is not None and plc.net.name == "tank"
    doc = loop.document()
    assert doc["symbols"]["min_temp"]["value"] == 2.0
    assert doc["kept_across"] == {"from": "mixer", "symbols": ["batches"]}
