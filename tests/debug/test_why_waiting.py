"""`softplc why` says why nothing moves (issue 39 item 6) against a real `softplc run`: a
program whose only transition waits for inputs no device drives. Without a transition, `why`
lists the longest waits with what blocks each, in net time (core/waiting.py, from the status
document); `why TRANSITION` of a waiting transition adds how long it has waited."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.debug.live import running
from tests.debug.test_why_api import IO, PROGRAM, cli
from tests.support import eventually, free_port, softplc_run


@pytest.fixture(scope="module")
def gate(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`softplc run gate.yaml --start`: `go` waits for `a and level >= 3`, which nothing
    makes true."""
    here = tmp_path_factory.mktemp("gate")
    (here / "gate.yaml").write_text(PROGRAM, encoding="utf-8")
    (here / "io.yaml").write_text(IO, encoding="utf-8")
    url = f"http://127.0.0.1:{free_port()}"
    with softplc_run([str(here / "gate.yaml"), "--start", "--api", url.removeprefix("http://"),
                      "--modbus", "off", "--opcua", "off", "--state-dir", str(here / "state"),
                      "--quiet", "--period", "10ms"], lambda: running(url)):
        yield url


def waits(url: str) -> dict[str, Any]:
    code, out, err = cli("why", "--api", url, "--json")
    assert code == 0, err
    answer: dict[str, Any] = json.loads(out)
    return answer


def test_why_without_a_transition_names_the_longest_wait_and_its_blockers(gate: str) -> None:
    answer = eventually(lambda: (w := waits(gate))["waiting"] and
                        w["waiting"][0]["for_s"] >= 0.3 and w, 15, "go waited 0.3 s")
    assert answer["state"] == "RUNNING"
    first = answer["waiting"][0]
    assert first["transition"] == "go" and first["symbols"] == ["a", "level"], first
    assert first["blockers"] == ["guard a and level >= 3: a is false with a = 0",
                                 "guard a and level >= 3: level >= 3 is false with level = 0"]
    code, out, err = cli("why", "--api", gate)
    assert code == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("why nothing moves (after scan ") and "net time" in lines[0]
    assert lines[1].startswith("  go waits ") and lines[1].endswith(
        " s: guard a and level >= 3: a is false with a = 0; guard a and level >= 3: "
        "level >= 3 is false with level = 0"), lines
    code, out, err = cli("why", "go", "--api", gate)
    assert code == 0, err
    assert out.startswith("go: ")
    said = [x for x in out.splitlines() if "in net time" in x]
    assert len(said) == 1 and said[0].startswith("  waited ") and said[0].endswith(
        " s in net time, enabled by the marking without firing (the longest wait of the "
        "net)"), out
    code, out, err = cli("why", "go", "--api", gate, "--json")
    assert code == 0 and json.loads(out)["waiting"]["transition"] == "go", err


def test_a_stopped_plc_waits_for_nothing(gate: str, tmp_path: Path) -> None:
    assert cli("stop", "--api", gate)[0] == 0
    try:
        assert eventually(lambda: cli("why", "--api", gate)[1].strip() == (
            "why: nothing waits (state STOPPED: only a RUNNING PLC waits)"), 10, "stopped")
    finally:
        assert cli("resume", "--api", gate)[0] == 0
    code, _, err = cli("why", "--trace", str(tmp_path / "none.jsonl"), "--api", gate)
    assert code == 1 and "--trace needs a TRANSITION" in err
