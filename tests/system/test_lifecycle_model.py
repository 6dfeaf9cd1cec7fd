"""The whole lifecycle as one model-based test (issue 26 item 5): a real `softplc run`
(supervisor, scan, communication and compile processes; Modbus slave, HTTP API and OPC UA on
free loopback ports) driving a Modbus TCP remote-I/O module inside the test, through random
sequences of cold and warm starts, SIGTERM/SIGINT/SIGKILL of the run, kill -9 of the scan,
communication and compile processes, downloads (offline, online, dry run, refused,
reconfiguration), lifecycle commands over HTTP, OPC UA and the CLI, HMI writes, forces, and
the module lost and back. After every step tests/system/checks.py holds every view of the PLC
to the model (tests/system/model.py); at the end nothing may be left behind.

Bounded in `make test` (a fixed seed, 3 sequences of up to 12 steps, no shrinking: 2.5-3 min
at load 12-15 on 2 cores); `SOFTPLC_FUZZ_SCALE=N` (`make fuzz`) runs N times the sequences,
twice as long, and shrinks a failure.
A failure prints the steps as Python (`state = LifecycleMachine()`, `state.rule(...)`, ...):
paste them into a test (tests/system/test_lifecycle_regressions.py shows how) to replay.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, Phase, settings
from hypothesis import seed as hseed
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    precondition,
    rule,
    run_state_machine_as_test,
)

from tests.fuzz.budget import record, scale, scaled, seed
from tests.system import probe
from tests.system.checks import Violation, agree, settle
from tests.system.model import EMPTY, Expect, Model
from tests.system.programs import BAD, PROGRAMS, Module, write_library
from tests.system.rig import EXIT_SLACK_S, EXIT_WITHIN_S, SAFE_WITHIN_S, Rig, wait_api

LIFECYCLE_DEADLINE_S = 5.0 + 1.0  # docs/operations.md: 5 s, and a reply within 1 s more
DOWNLOAD_BOUND_S = 25.0  # the contract allows 60 s; a 5-place program compiles in well under 1
RESTART_WITHIN_S = 30.0  # a killed child is back (restart backoff + a loaded machine's spawn)
KILLS_PER_RUN = 3  # the supervisor gives up after 5 deaths in 60 s: stay clear of that


class LifecycleMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.base = Path(tempfile.mkdtemp(prefix="softplc-system-"))
        self.module = Module()
        self.module.start()
        self.library = write_library(self.base / "programs", self.module.port)
        self.rig = Rig(self.base, self.library, self.module)
        self.model = Model()
        self.scan_kills = self.comm_kills = 0

    # -- starts and ends of the whole run ---------------------------------------------------

    @initialize(program=st.sampled_from(["v1", None]), start=st.booleans())
    def cold_start(self, program: str | None, start: bool) -> None:
        self._cold(program, start)

    @rule(how=st.sampled_from(["SIGTERM", "SIGINT", "SIGKILL"]), start=st.booleans())
    def warm_restart(self, how: str, start: bool) -> None:
        state_dir = self._end(how)
        self.model.warm_start(start)
        self._begin(state_dir, None, start)

    @rule(program=st.sampled_from(["v1", None]), start=st.booleans())
    def cold_restart(self, program: str | None, start: bool) -> None:
        self._end("SIGTERM")
        self._cold(program, start)

    @rule(how=st.sampled_from(["SIGTERM", "SIGINT"]), delay_ms=st.integers(0, 1500),
          start=st.booleans())
    def signal_during_start(self, how: str, delay_ms: int, start: bool) -> None:
        """A run told to stop while it starts (its children spawned, the program maybe not
        loaded yet) stops as any other: exit 0 within 2 s, outputs safe; then a warm start."""
        state_dir = self._end("SIGTERM")
        run = self.rig.start(state_dir, None, True)
        settle(run.children, bool, "the supervisor spawned its children", timeout_s=30)
        time.sleep(delay_ms / 1000)
        self.model.warm_start(True)
        self._end(how)
        self.model.warm_start(start)
        self._begin(state_dir, None, start)

    def _cold(self, program: str | None, start: bool) -> None:
        self.model.cold_start(program, start)
        self._begin(self.rig.new_state_dir(), program, start)

    def _begin(self, state_dir: Path, program: str | None, start: bool) -> None:
        wait_api(self.rig.start(state_dir, program, start))
        self.scan_kills = self.comm_kills = 0

    def _end(self, how: str) -> Path:
        run = self.rig.run
        assert run is not None
        ending = self.rig.stop(how)
        if ending.safe_s is not None and ending.safe_s > SAFE_WITHIN_S:
            raise Violation(f"{how}: outputs safe only after {ending.safe_s:.2f} s "
                            f"(docs/faults.md: within {SAFE_WITHIN_S} s)")
        if how != "SIGKILL":
            if ending.code != 0 or ending.exit_s > EXIT_WITHIN_S + EXIT_SLACK_S:
                raise Violation(f"{how}: exit code {ending.code} after {ending.exit_s:.1f} s "
                                f"(docs/operations.md: 0 within {EXIT_WITHIN_S} s); log: "
                                f"{ending.log_tail}")
            left = [x for x in self.rig.leftovers() if f"_{run.proc.pid}_" in x]
            if left:
                raise Violation(f"{how}: the run left {left}")
        return run.state_dir

    # -- kill -9 of one process -------------------------------------------------------------

    @precondition(lambda self: self.scan_kills < KILLS_PER_RUN)
    @rule()
    def kill_scan_process(self) -> None:
        run = self._run()
        before = run.api.status()
        # Wait for a retain snapshot taken after the last step: what ran since the newest
        # snapshot is lost by design (docs/retain.md), the test does not count that window.
        writes = int((before.get("retain") or {}).get("writes") or 0)
        if self.model.program is not None:  # without a program there is nothing to retain
            settle(run.api.status, lambda s: int((s.get("retain") or {}).get("writes") or 0)
                   >= writes + 2, "two retain snapshots (every 1 s)", timeout_s=15)
        last = probe.block(run).scan_count  # the last count published before the kill
        os.kill(int(before["scan_pid"]), signal.SIGKILL)
        self.model.scan_floor = max(self.model.scan_floor, last)
        self.scan_kills += 1
        restarts = int(before.get("restarts") or 0)
        settle(run.api.status, lambda s: int(s.get("restarts") or 0) == restarts + 1
               and not s.get("stale") and s.get("scan_pid") != before["scan_pid"],
               "the scan process restarted warm", timeout_s=RESTART_WITHIN_S, step_s=0.1)

    @precondition(lambda self: self.comm_kills < KILLS_PER_RUN)
    @rule(service=st.sampled_from(["comm", "opcua"]))
    def kill_service_process(self, service: str) -> None:
        """kill -9 of the communication process (Modbus, HTTP) or the OPC UA process."""
        run = self._run()
        port = run.api_port if service == "comm" else run.opcua
        assert port is not None
        pid = run.listener(port)
        assert pid is not None, f"no process of {run.children()} listens on {port}"
        os.kill(pid, signal.SIGKILL)
        self.comm_kills += 1
        settle(lambda: run.listener(port), lambda new: new is not None and new != pid,
               f"the {service} process restarted", timeout_s=RESTART_WITHIN_S, step_s=0.1)
        wait_api(run, RESTART_WITHIN_S)

    @rule()
    def kill_compile_process(self) -> None:
        run = self._run()
        pid = int((run.api.status().get("compile_process") or {}).get("pid") or 0)
        if pid > 0:
            with contextlib.suppress(ProcessLookupError):  # gone: a download starts one
                os.kill(pid, signal.SIGKILL)

    @rule(program=st.sampled_from(["v1", "v2", "other"]), online=st.booleans(),
          delay_ms=st.integers(0, 300))
    def download_while_compile_killed(self, program: str, online: bool, delay_ms: int) -> None:
        """The compile process dies during a download: applied or refused, never both."""
        run = self._run()
        expect = self.model.expect_download(program, online)
        result: list[probe.Outcome] = []
        sender = threading.Thread(target=lambda: result.append(
            probe.http_download(run, PROGRAMS[program], online, f"{program}.yaml")[0]))
        sender.start()
        time.sleep(delay_ms / 1000)
        self.kill_compile_process()
        sender.join(DOWNLOAD_BOUND_S + 5)
        if not result:
            raise Violation(f"download of {program} never answered after its compile process "
                            "was killed")
        outcome = result[0]
        self._within(outcome, DOWNLOAD_BOUND_S, f"download {program}")
        if outcome.kind == "applied" and expect.applied:
            self.model.apply_download(program, expect)
        elif outcome.kind == "applied" or (outcome.kind != "refused" and outcome.kind
                                             != "expired"):
            raise Violation(f"download {program} (online={online}) with the compile process "
                            f"killed: {outcome.kind} ({outcome.detail}); model: {expect}")

    # -- commands ---------------------------------------------------------------------------

    @rule(channel=st.sampled_from(["http", "opcua", "cli"]),
          command=st.sampled_from(["start", "stop", "resume", "reset", "kill"]))
    def lifecycle(self, channel: str, command: str) -> None:
        run = self._run()
        expect = self.model.expect_command(command)
        if channel == "http":
            outcome = probe.http_command(run, command)
        elif channel == "opcua":
            outcome = probe.opcua_command(run, command)
        else:
            outcome = probe.cli(run, command)
        self._within(outcome, LIFECYCLE_DEADLINE_S, f"{channel} {command}")
        self._judge(outcome, expect, f"{channel} {command}")
        self.model.apply_command(command, expect)

    @rule(channel=st.sampled_from(["http", "opcua", "cli"]),
          program=st.sampled_from(["v1", "v2", "other", "bad"]), online=st.booleans())
    def download(self, channel: str, program: str, online: bool) -> None:
        run = self._run()
        expect = self.model.expect_download(program, online)
        text = BAD if program == "bad" else PROGRAMS[program]
        if channel == "http":
            outcome = probe.http_download(run, text, online, f"{program}.yaml")[0]
        elif channel == "opcua":
            outcome = probe.opcua_download(run, text, online, f"{program}.yaml")
        else:
            path = self.base / "programs" / f"{program}.yaml"
            path.write_text(text, encoding="utf-8")
            outcome = probe.cli(run, "download", str(path), *(["--online"] if online else []))
        self._within(outcome, DOWNLOAD_BOUND_S, f"{channel} download {program}")
        self._judge(outcome, expect, f"{channel} download {program} online={online}")
        self.model.apply_download(program, expect)

    @rule(program=st.sampled_from(["v1", "v2", "other", "bad"]), online=st.booleans())
    def dry_run(self, program: str, online: bool) -> None:
        run = self._run()
        expect = self.model.expect_download(program, online)
        text = BAD if program == "bad" else PROGRAMS[program]
        outcome, plan = probe.http_download(run, text, online, f"{program}.yaml", dry_run=True)
        self._within(outcome, DOWNLOAD_BOUND_S, f"dry run {program}")
        if program == "bad":
            self._judge(outcome, expect, "dry run of a bad program")
        elif outcome.kind != "applied" or bool(plan.get("accepted")) != expect.applied:
            raise Violation(f"dry run {program} online={online}: {outcome.kind}, plan "
                            f"accepted={plan.get('accepted')} ({plan.get('verdict')}); the "
                            f"model: {expect}; reply: {outcome.detail}")

    @rule(cmd=st.booleans(), word=st.integers(0, 65535))
    def hmi_write(self, cmd: bool, word: int) -> None:
        run = self._run()
        probe.hmi_write(run, cmd, word)
        self.model.cmd, self.model.word = cmd, word
        settle(lambda: probe.memory(run), lambda m: m == (cmd, word),
               "the HMI write shows at the next scans", timeout_s=3)

    @rule(value=st.integers(0, 1))
    def force(self, value: int) -> None:
        run = self._run()
        refused = self.model.state == EMPTY or self.model.program is None
        outcome = probe._from_http(time.monotonic(), lambda: run.api.force("lamp2", value))
        self._judge(outcome, Expect(not refused, self.model.state), f"force lamp2 {value}")
        if not refused:
            self.model.forced["lamp2"] = value

    @rule()
    def unforce(self) -> None:
        outcome = probe._from_http(time.monotonic(), lambda: self._run().api.unforce())
        self._judge(outcome, Expect(True, self.model.state), "unforce everything")
        self.model.forced.clear()

    # -- the device -------------------------------------------------------------------------

    @precondition(lambda self: self.model.device_up)
    @rule()
    def device_lost(self) -> None:
        self.module.stop()
        self.model.device_lost()
        if self.model.program is None:
            return  # no program, no driver: nothing to notice
        settle(self._run().api.status, lambda s: (s.get("health") or {}).get("rio") != "ok",
               "status shows the module lost")

    @precondition(lambda self: not self.model.device_up)
    @rule()
    def device_back(self) -> None:
        self.module.start()
        self.model.device_up = True
        if self.model.program is None:
            return
        settle(self._run().api.status, lambda s: (s.get("health") or {}).get("rio") == "ok",
               "status shows the module back", timeout_s=10)

    # -- every step -------------------------------------------------------------------------

    @invariant()
    def views_agree_with_the_model(self) -> None:
        if self.rig.run is not None:
            agree(self.rig.run, self.model, self.library, self.module)

    def teardown(self) -> None:
        try:
            if self.rig.run is not None:
                self._end("SIGTERM")
            left = self.rig.leftovers()
            if left:
                raise Violation(f"left behind at the end: {left}")
        finally:
            self.rig.close()
            self.module.dispose()
            shutil.rmtree(self.base, ignore_errors=True)

    # -- helpers ----------------------------------------------------------------------------

    def _run(self) -> Any:
        assert self.rig.run is not None
        return self.rig.run

    @staticmethod
    def _within(outcome: probe.Outcome, bound_s: float, what: str) -> None:
        if outcome.kind in ("none", "pending") or outcome.seconds > bound_s:
            raise Violation(f"{what}: {outcome.kind} after {outcome.seconds:.1f} s (bound "
                            f"{bound_s} s): {outcome.detail}")

    def _judge(self, outcome: probe.Outcome, expect: Expect, what: str) -> None:
        if outcome.kind == "expired":
            raise Violation(f"{what}: expired on an idle PLC ({outcome.detail})")
        if (outcome.kind == "applied") != expect.applied:
            want = "applied" if expect.applied else "refused"
            raise Violation(f"{what} in {self.model.state}: {outcome.kind} "
                            f"({outcome.detail}); the model: {want} ({expect.why})")


def lifecycle_settings(examples: int = 3, steps: int = 12) -> settings:
    """`examples` sequences of up to `steps` steps at scale 1; a long run (`make fuzz`) tries
    SOFTPLC_FUZZ_SCALE times the sequences, twice as long, and shrinks what fails."""
    long_run = scale() > 1
    return settings(
        max_examples=scaled(examples), stateful_step_count=steps * (2 if long_run else 1),
        deadline=None, database=None, report_multiple_bugs=False, print_blob=True,
        phases=(Phase.explicit, Phase.generate, *((Phase.shrink,) if long_run else ())),
        suppress_health_check=list(HealthCheck))


@pytest.mark.slow
def test_the_lifecycle_holds_to_its_model() -> None:
    t0 = time.monotonic()
    config = lifecycle_settings()
    # a fixed seed (reproducible in CI); SOFTPLC_FUZZ_SEED explores other sequences
    run_state_machine_as_test(hseed(seed(265))(LifecycleMachine), settings=config)
    record("system_lifecycle", examples=config.max_examples,
           steps=config.stateful_step_count, seconds=round(time.monotonic() - t0))
