"""The programs the whole-system test downloads, and the remote-I/O module they drive.

Owns: the io images (one Modbus TCP remote-I/O module on 127.0.0.1), the program texts (a
first version, an online change of it, another program on new devices, a bad one), their
hashes as the PLC computes them, and `Module`, a RemoteIoDevice whose inputs hold their
values from the module's first answer on.
Does not know: the PLC's processes, the model.

Coils of the module: 0 `lamp` (on while the program runs), 1 `lamp2` (follows the HMI bit
`cmd`, %MX0.0), 2 `alarm` (on only if the net saw `go` low; the module holds `go` high from
its first answer, so a PLC that never acts on inputs it has not read never sets it).
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from pathlib import Path

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from softplc.program.compiler import compile_text
from tests.devices.remote_io_device import FC_HR, SIZE, RemoteIoDevice

COILS = (0, 1, 2)  # lamp, lamp2, alarm: every output the programs drive, all safe 0
LAMP, LAMP2, ALARM = COILS

IO = """\
drivers:
  rio: {{kind: modbus, host: 127.0.0.1, port: {port}, timeout_s: {timeout_s},
         reconnect_min_s: 0.05, reconnect_max_s: 0.3, startup_s: 1}}
symbols:
  go:    {{address: "%IX0.0", channel: "di:0", description: "held high by the module"}}
  lamp:  {{address: "%QX0.0", channel: "coil:0", safe: false}}
  lamp2: {{address: "%QX0.1", channel: "coil:1", safe: false}}
  alarm: {{address: "%QX0.2", channel: "coil:2", safe: false}}
  cmd:   {{address: "%MX0.0", description: "HMI bit"}}
  word:  {{address: "%MW0", type: word, description: "HMI word"}}
"""

_BODY = """\
places:
  on: {tokens: 1, outputs: [lamp]}
  idle: {tokens: 1}
  armed: {outputs: [lamp2]}
  watching: {tokens: 1}
  blind: {outputs: [alarm]}
transitions:
  arm: {from: [idle], to: [armed], when: cmd}
  disarm: {from: [armed], to: [idle], when: not cmd}
  saw_low: {from: [watching], to: [blind], when: not go}
"""

PROGRAMS: dict[str, str] = {
    # the first program, and its online change (one place more: another hash, same name)
    "v1": "program: lamp\nio_image: io.yaml\n" + _BODY,
    "v2": "program: lamp\nio_image: io.yaml\n" + _BODY.replace(
        "  blind: {outputs: [alarm]}\n", "  blind: {outputs: [alarm]}\n  spare: {tokens: 1}\n"),
    # another program on other devices (the same module, another driver configuration): an
    # online download while RUNNING is a reconfiguration and goes ahead without `replace`
    "other": "program: other\nio_image: io2.yaml\n" + _BODY,
}
BAD = ("program: lamp\nio_image: io.yaml\nplaces:\n  on: {tokens: -1}\n"
       "transitions:\n  t: {from: [nowhere], to: [on]}\n")


@dataclass(frozen=True)
class Library:
    """The programs directory of one test run and each program's hash."""

    root: Path
    hashes: dict[str, str]

    def path(self, key: str) -> Path:
        return self.root / f"{key}.yaml"


def write_library(root: Path, port: int) -> Library:
    """The io images and programs under `root` (the PLC's --programs-dir), with hashes."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "io.yaml").write_text(IO.format(port=port, timeout_s=2.0), encoding="utf-8")
    (root / "io2.yaml").write_text(IO.format(port=port, timeout_s=1.9), encoding="utf-8")
    hashes = {}
    for key, text in PROGRAMS.items():
        (root / f"{key}.yaml").write_text(text, encoding="utf-8")
        hashes[key] = compile_text(text, str(root / f"{key}.yaml"), root).program_hash
    return Library(root, hashes)


class Module(RemoteIoDevice):
    """The remote-I/O module with discrete input 0 (`go`) high from its first answer on,
    also after a restart: the test never lowers it."""

    async def _start(self) -> None:
        # RemoteIoDevice._start with the input set before the server listens (set after,
        # a request could be answered with the input still low in between).
        from tests.devices import remote_io_device as rio

        rio._INTERNAL.set(True)
        bits = [SimData(0, values=[False] * SIZE, datatype=DataType.BITS)]
        inputs = [SimData(0, values=[True] + [False] * (SIZE - 1), datatype=DataType.BITS)]
        words = [SimData(0, values=[0] * SIZE, datatype=DataType.REGISTERS)]
        device = SimDevice(id=0, simdata=(bits, inputs, words, list(words)),
                           action=self._action)
        self.server = ModbusTcpServer(device, address=("127.0.0.1", self.port),
                                      trace_pdu=self._trace)
        await self.server.serve_forever(background=True)
        await self.server.async_setValues(0, FC_HR, self.watchdog_register,
                                          [self.initial_timeout_ms])
        self._armed = self._tripped = False
        self._last_beat, self._beat_at = 0, time.monotonic()
        self._monitor = asyncio.ensure_future(self._watch())
