"""The remote-softplc driver: the device interface's program-handling group (seed paper,
Fig. 2) against another softplc's HTTP API, so a cell-level softplc coordinates stations.

Owns: RemoteSoftplc (download/start/stop/reset/resume/kill, Python-style raising and the
paper's 0/-1 facade), the mapping of API answers to ProgramHandlingError/DeviceUnavailable.
Does not know: HTTP details (softplc.api.client), the local scan, what the programs do.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from softplc.api.client import DEFAULT_URL, ApiClient, ApiError, ApiUnreachable
from softplc.core.lifecycle import Command, PlcState
from softplc.devices.driver import DeviceUnavailable, ProgramHandlingError
from softplc.interface.facade import PaperProgramHandling

_UNAVAILABLE = frozenset({401, 503})  # not the program's fault: no usable device behind


class RemoteProgramRefused(ProgramHandlingError):
    """The remote softplc refused: `problems` lists every problem of a bad program."""

    def __init__(self, message: str, status: int, problems: Sequence[str] = ()) -> None:
        self.status = status
        self.problems = tuple(problems)
        super().__init__("\n".join([message, *self.problems]))


class RemoteSoftplc(PaperProgramHandling):
    """Another softplc, handled like a device: `url` is its API (e.g. http://10.0.0.7:8080),
    `token` its bearer token when it is bound off loopback."""

    def __init__(self, url: str = DEFAULT_URL, token: str | None = None,
                 timeout_s: float = 10.0) -> None:
        self.url = url
        self._client = ApiClient(url, token, timeout_s)
        self._names: frozenset[str] = frozenset()  # what the last download may be called
        self.last_error = ""

    def __repr__(self) -> str:
        return f"RemoteSoftplc({self.url!r})"

    # -- Python style: raise DeviceError subclasses -----------------------------------------

    def download_program(self, file: str | Path, location: str | Path | None = None, *,
                         online: bool = False) -> str:
        """Send `file` (found in the directory `location`, if given); loaded STOPPED, or
        swapped in while RUNNING when `online`. Returns the remote's message."""
        path = Path(location) / file if location else Path(file)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ProgramHandlingError(f"download of {path} refused: cannot read it: {exc}"
                                       ) from None
        reply = self._call(lambda: self._client.download_text(text, online, path.name))
        self._names = frozenset({str(file), str(path), path.name, path.stem})
        return str(reply.get("message", ""))

    def status(self) -> dict[str, Any]:
        return self._call(self._client.status)

    def state(self) -> PlcState:
        return _state(self.status())

    def _control(self, command: Command, program: str | None) -> PlcState:
        if program:
            holds = self.status().get("program")
            if program not in self._names | {holds}:
                raise ProgramHandlingError(f"{command.value} {program!r} refused: {self.url} "
                                           f"holds program {holds!r}")
        return _state(self._call(lambda: self._client.command(command.value)))

    def _call(self, action: Callable[[], dict[str, Any]]) -> dict[str, Any]:
        try:
            return action()
        except ApiUnreachable as exc:
            raise DeviceUnavailable(str(exc)) from None
        except ApiError as exc:
            if exc.status in _UNAVAILABLE:
                raise DeviceUnavailable(f"{self.url}: {exc.message}") from None
            raise RemoteProgramRefused(f"{self.url}: {exc.message}", exc.status,
                                       exc.problems) from None

    # -- the paper's facade (Fig. 2): download/start/.../kill come from PaperProgramHandling


def _state(answer: dict[str, Any]) -> PlcState:
    try:
        return PlcState[str(answer.get("state"))]
    except KeyError:
        raise DeviceUnavailable(f"the remote answered an unknown state {answer.get('state')!r}"
                                ) from None
