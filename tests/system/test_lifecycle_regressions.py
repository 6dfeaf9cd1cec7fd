"""Short sequences of the lifecycle model test (test_lifecycle_model.py), kept as they are
printed on a failure: each replays a real `softplc run` through the same rules and checks
every view of the PLC against the model after every step (a few seconds each).

The sequences are the shortest found for each broken promise (issue 26 item 5); they fail on
the code that had the defect named in their docstring.
"""

from __future__ import annotations

import pytest

from tests.system import probe
from tests.system.programs import PROGRAMS
from tests.system.rig import ROOT, wait_api
from tests.system.test_lifecycle_model import LifecycleMachine

pytestmark = pytest.mark.slow


def test_a_download_after_a_warm_restart_is_applied() -> None:
    """After a warm start the first download hung and no later command was applied."""
    state = LifecycleMachine()
    try:
        state.cold_start(program="v1", start=False)
        state.views_agree_with_the_model()
        state.warm_restart(how="SIGTERM", start=False)
        state.views_agree_with_the_model()
        state.download(channel="http", program="v2", online=False)
        state.views_agree_with_the_model()
        state.lifecycle(channel="http", command="start")
        state.views_agree_with_the_model()
    finally:
        state.teardown()


def test_sigterm_with_opcua_leaves_the_outputs_safe_within_one_second() -> None:
    """SIGTERM of a running PLC serving OPC UA left a remote output on for about 5 s."""
    state = LifecycleMachine()
    try:
        state.cold_start(program="v1", start=False)
        state.views_agree_with_the_model()
        state.lifecycle(channel="http", command="start")  # the module answered by now
        state.views_agree_with_the_model()
        state.warm_restart(how="SIGTERM", start=False)
        state.views_agree_with_the_model()
    finally:
        state.teardown()


def test_the_scan_count_goes_on_after_the_scan_process_is_killed() -> None:
    """The scan count went back to the retain snapshot's after a warm restart."""
    state = LifecycleMachine()
    try:
        state.cold_start(program="v1", start=False)
        state.views_agree_with_the_model()
        state.kill_scan_process()
        state.views_agree_with_the_model()
    finally:
        state.teardown()


def test_a_cold_start_never_fires_on_inputs_no_device_delivered() -> None:
    """The net fired `saw_low` on `go` low before the module had answered once (the module
    holds `go` high from its first answer on)."""
    state = LifecycleMachine()
    try:
        state.cold_start(program="v1", start=True)
        state.views_agree_with_the_model()
        state.cold_restart(program="v1", start=True)
        state.views_agree_with_the_model()
    finally:
        state.teardown()


def test_sigterm_while_the_run_starts_exits_cleanly() -> None:
    """SIGTERM just after the supervisor spawned its children killed it (exit -15) instead
    of stopping everything (exit 0)."""
    state = LifecycleMachine()
    try:
        state.cold_start(program="v1", start=False)
        state.views_agree_with_the_model()
        state.signal_during_start(how="SIGTERM", delay_ms=0, start=False)
        state.views_agree_with_the_model()
    finally:
        state.teardown()


def test_a_run_without_a_program_takes_plain_downloads_from_its_programs_dir() -> None:
    """`softplc run --programs-dir DIR` without a program argument (the systemd unit's way)
    refused every plain-text download whose io image is in DIR when DIR is not under the
    current directory: "io_image: path 'io.yaml' leaves the program directory"."""
    state = LifecycleMachine()
    try:
        run = state.rig.start(state.rig.new_state_dir(), None, False, cwd=ROOT)
        wait_api(run)
        outcome, _ = probe.http_download(run, PROGRAMS["v1"], False, "v1.yaml")
        assert outcome.kind == "applied", outcome.detail
    finally:
        state.teardown()
