"""Short sequences of the lifecycle model test (test_lifecycle_model.py), kept as they are
printed on a failure: each replays a real `softplc run` through the same rules and checks
every view of the PLC against the model after every step (a few seconds each).

The sequences are the shortest found for each broken promise (issue 26 item 5); they fail on
the code that had the defect named in their docstring.
"""

from __future__ import annotations

import pytest

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
