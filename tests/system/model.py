"""The model the whole-system test holds a real `softplc run` to: what the documents promise.

Owns: the lifecycle table of docs/design.md section 4 written out again (an oracle of its
own, not the code's table), what a download does in each state (docs/api.md, online change),
forces (design.md section 10), the device fault policy `fault` (docs/faults.md), what a warm
or cold start restores (docs/retain.md) and the OPC UA state names (docs/opcua.md).
Does not know: processes, sockets, time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

EMPTY, STOPPED, RUNNING, KILLED, FAULTED = "EMPTY", "STOPPED", "RUNNING", "KILLED", "FAULTED"

# (state, command) -> next state; a pair that is absent is refused and changes nothing.
# STOPPED is two stages (design.md section 4, issue 29): READY (initial marking: after a
# download or a reset) takes `start`, SUSPENDED (a stop kept the marking) takes `resume`.
READY, SUSPENDED = "STOPPED/READY", "STOPPED/SUSPENDED"
TABLE: dict[tuple[str, str], str] = {
    (READY, "start"): RUNNING, (READY, "reset"): READY, (READY, "kill"): KILLED,
    (SUSPENDED, "resume"): RUNNING, (SUSPENDED, "reset"): READY, (SUSPENDED, "kill"): KILLED,
    (RUNNING, "stop"): SUSPENDED, (RUNNING, "kill"): KILLED,
    (KILLED, "reset"): READY,
    (FAULTED, "reset"): READY, (FAULTED, "kill"): KILLED,
}
DROPS_FORCES = ("reset",)  # start (from READY) and resume keep them
NAMES = {"v1": "lamp", "v2": "lamp", "other": "other"}
IO_OF = {"v1": "io.yaml", "v2": "io.yaml", "other": "io2.yaml"}
MARKED_ONLY_IN = {"v2": "spare"}  # a place with a token that the other version lacks


@dataclass(frozen=True)
class Expect:
    """A command's expected fate: applied (and the state after) or refused."""

    applied: bool
    state: str
    why: str = ""


@dataclass
class Model:
    state: str = EMPTY
    program: str | None = None  # the last program the PLC accepted (a key of PROGRAMS)
    stopped_by: str = "load"  # in STOPPED: "stop" (SUSPENDED) or "load" (READY)
    forced: dict[str, int] = field(default_factory=dict)
    cmd: bool | None = False  # HMI memory; None: not known (not promised across a download)
    word: int | None = 0
    device_up: bool = True
    scan_floor: int = 0  # the highest scan count seen since the state directory was new

    # -- lifecycle commands -----------------------------------------------------------------

    @property
    def stage(self) -> str:
        if self.state != STOPPED:
            return self.state
        return SUSPENDED if self.stopped_by == "stop" else READY

    def expect_command(self, command: str) -> Expect:
        nxt = TABLE.get((self.stage, command))
        if nxt is None:
            return Expect(False, self.state, f"{command} is not accepted in {self.stage}")
        if nxt == RUNNING and not self.device_up:
            return Expect(True, FAULTED, "a start or resume with a failed device faults")
        return Expect(True, nxt)

    def apply_command(self, command: str, expect: Expect) -> None:
        if not expect.applied:
            return
        self.state = expect.state.split("/")[0]
        if command in DROPS_FORCES:
            self.forced.clear()
        if expect.state in (READY, SUSPENDED):
            self.stopped_by = "stop" if expect.state == SUSPENDED else "load"

    # -- downloads ------------------------------------------------------------------------------

    def expect_download(self, key: str, online: bool) -> Expect:
        if key == "bad":
            return Expect(False, self.state, "a program with problems")
        if self.state != RUNNING:
            return Expect(True, STOPPED, "a download loads the program stopped")
        if not online:
            return Expect(False, RUNNING, "a download while RUNNING needs online")
        assert self.program is not None
        if NAMES[key] == NAMES[self.program]:
            dropped = MARKED_ONLY_IN.get(self.program)
            if dropped and dropped != MARKED_ONLY_IN.get(key):
                return Expect(False, RUNNING, f"online change would drop the token in {dropped}")
            return Expect(True, RUNNING, "online change")
        if IO_OF[key] == IO_OF[self.program]:
            return Expect(False, RUNNING, "another program on the same devices needs replace")
        return Expect(True, RUNNING, "reconfiguration: another program on new devices")

    def apply_download(self, key: str, expect: Expect) -> None:
        if not expect.applied:
            return
        self.program = key
        if self.state != RUNNING:
            self.stopped_by = "load"
        self.state = expect.state
        self.cmd = self.word = None  # the documents promise nothing about memory here

    # -- devices, starts ------------------------------------------------------------------------

    def device_lost(self) -> None:
        self.device_up = False
        if self.state == RUNNING:  # on_failure: fault (the default)
            self.state = FAULTED

    def warm_start(self, start: bool) -> None:
        """A whole new run on the same state directory, no program on the command line: the
        boot program and its final snapshot (docs/retain.md, at start)."""
        if self.program is None:  # nothing to restore: a cold start, counting from 0
            self.state, self.scan_floor = EMPTY, 0
            return
        if self.state == RUNNING and not start:  # restored, timers frozen: as after a stop
            self.state, self.stopped_by = STOPPED, "stop"
        if self.state == RUNNING and not self.device_up:
            self.state = FAULTED

    def cold_start(self, program: str | None, start: bool) -> None:
        """A whole new run on a new state directory."""
        self.program, self.forced, self.cmd, self.word, self.scan_floor = program, {}, False, 0, 0
        self.stopped_by = "load"
        if program is None:
            self.state = EMPTY
        elif not start:
            self.state = STOPPED
        else:
            self.state = RUNNING if self.device_up else FAULTED

    # -- what the PLC should say ------------------------------------------------------------------

    def opcua_states(self) -> set[str]:
        """PLC.Program.CurrentState texts the model allows (docs/opcua.md)."""
        if self.state == RUNNING:
            return {"Running"}
        if self.state == STOPPED:
            return {"Suspended"} if self.stopped_by == "stop" else {"Ready"}
        return {"Halted"}
