"""The seed paper's program-handling functions (Fig. 2) with its return codes.

Owns: download/start/stop/reset/resume/kill returning 0 on success and -1 on a DeviceError
(the message kept in `last_error`), on top of the Python-style `*_program` methods, which
go to the device's `_control`. Does not know: what a device is (local PLC or a remote
softplc).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from softplc.core.lifecycle import Command, PlcState
from softplc.devices.driver import DeviceError


class PaperProgramHandling:
    """Mix into a device that has download_program and `_control(command, program)`: the
    program commands of the paper, as exceptions (start_program ...) and as return codes
    (start ...)."""

    last_error: str = ""

    download_program: Callable[..., Any]

    def _control(self, command: Command, program: str | None) -> PlcState:
        raise NotImplementedError  # the device's own: a local PLC or the HTTP API

    def start_program(self, program: str | None = None) -> PlcState:
        """Cold start: initial marking."""
        return self._control(Command.START, program)

    def stop_program(self, program: str | None = None) -> PlcState:
        """Graceful stop: outputs safe, marking and timers frozen."""
        return self._control(Command.STOP, program)

    def reset_program(self, program: str | None = None) -> PlcState:
        return self._control(Command.RESET, program)

    def resume_program(self, program: str | None = None) -> PlcState:
        """Warm start: kept marking, timers shifted by the time spent stopped."""
        return self._control(Command.RESUME, program)

    def kill_program(self, program: str | None = None) -> PlcState:
        return self._control(Command.KILL, program)

    def download(self, file: str | Path, location: str | Path | None = None) -> int:
        return self._code(lambda: self.download_program(file, location))

    def start(self, program: str | None = None) -> int:
        return self._code(lambda: self.start_program(program))

    def stop(self, program: str | None = None) -> int:
        return self._code(lambda: self.stop_program(program))

    def reset(self, program: str | None = None) -> int:
        return self._code(lambda: self.reset_program(program))

    def resume(self, program: str | None = None) -> int:
        return self._code(lambda: self.resume_program(program))

    def kill(self, program: str | None = None) -> int:
        return self._code(lambda: self.kill_program(program))

    def _code(self, call: Callable[[], object]) -> int:
        try:
            call()
        except DeviceError as exc:
            self.last_error = str(exc)
            return -1
        self.last_error = ""
        return 0
