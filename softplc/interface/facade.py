"""The seed paper's program-handling functions (Fig. 2) with its return codes.

Owns: download/start/stop/reset/resume/kill returning 0 on success and -1 on a DeviceError
(the message kept in `last_error`), on top of the Python-style `*_program` methods that a
device class provides. Does not know: what a device is (local PLC or a remote softplc).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from softplc.devices.driver import DeviceError


class PaperProgramHandling:
    """Mix into a class that has download_program, start_program, ... kill_program."""

    last_error: str = ""

    download_program: Callable[..., Any]
    start_program: Callable[[str | None], Any]
    stop_program: Callable[[str | None], Any]
    reset_program: Callable[[str | None], Any]
    resume_program: Callable[[str | None], Any]
    kill_program: Callable[[str | None], Any]

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
