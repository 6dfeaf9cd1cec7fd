"""`softplc why` against a real `softplc run` (issue 32's done-when): the transport PLC
started as `make run` starts it, then a downloaded program whose inputs no device drives,
forced from the CLI; GET /api/v1/why/{transition} answers in the communication process."""

from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient
from softplc.cli import main
from tests.debug.live import transport_plc
from tests.support import eventually

ROOT = Path(__file__).resolve().parents[2]
PROGRAM = """program: gate
io_image: io.yaml
places: {p: {tokens: 1}, q: {}}
transitions:
  go: {from: [p], to: [q], when: "a and level >= 3"}
"""
IO = """symbols:
  a: {address: "%IX0.0", type: bool, driver: none}
  level: {address: "%IW0", type: word, driver: none}
"""


def cli(*args: str) -> tuple[int, str, str]:
    """A `softplc` command in this process (the server is the process under test)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(args))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """`softplc run programs/transport.yaml --plant transport --start` (make run's PLC)."""
    with transport_plc(tmp_path_factory) as (url, _):
        yield url


def why(url: str, name: str) -> dict[str, Any]:
    code, out, err = cli("why", name, "--api", url, "--json")
    assert code == 0, err
    answer: dict[str, Any] = json.loads(out)
    return answer


def test_why_hand_over_names_its_blocker_then_follows_a_force(server: str) -> None:
    code, out, err = cli("why", "hand_over", "--api", server)
    assert code == 0, err
    assert out.startswith("hand_over: ") and "(the next round, after scan " in out
    answer = why(server, "hand_over")
    assert answer["program"] == "transport" and answer["state"] == "RUNNING"
    if not answer["fires"]:  # a place or an input (symbol) is named
        assert any(r.get("place") or r.get("symbols") for r in answer["reasons"]), answer
    assert cli("force", "s1_i", "1", "--api", server)[0] == 0
    try:
        # c1.start reads s1_i: once the board shows the force, it no longer blames s1_i.
        start = eventually(lambda: (w := why(server, "c1.start")) and any(
            r["kind"] == "forced" for r in w["reasons"]) and w, 10, "the force in why")
        assert "s1_i is forced to 1 (read by its guard)" in [r["text"] for r in start["reasons"]]
        assert not any("s1_i is false" in r["text"] for r in start["reasons"]), start
        after = why(server, "hand_over")
        assert after["fires"] or after["reasons"], after
    finally:
        cli("unforce", "--api", server)
    code, _, err = cli("why", "no_such", "--api", server)
    assert code == 1 and "no transition 'no_such' in program transport" in err


def test_a_downloaded_program_is_explained_value_by_value(server: str, tmp_path: Path) -> None:
    (tmp_path / "gate.yaml").write_text(PROGRAM, encoding="utf-8")
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    assert cli("stop", "--api", server)[0] == 0
    code, _, err = cli("download", str(tmp_path / "gate.yaml"), "--api", server)
    assert code == 0, err
    assert cli("start", "--api", server)[0] == 0
    first = eventually(lambda: (w := why(server, "go"))["program"] == "gate" and w, 10,
                       "the new program explained")
    assert [r["text"] for r in first["reasons"]] == [
        "guard a and level >= 3: a is false with a = 0",
        "guard a and level >= 3: level >= 3 is false with level = 0"]
    assert cli("force", "a", "1", "--api", server)[0] == 0
    forced = eventually(lambda: (w := why(server, "go"))["reasons"][-1]["kind"] == "forced"
                        and w, 10, "the force in why")
    assert [r["text"] for r in forced["reasons"]] == [
        "guard a and level >= 3: level >= 3 is false with level = 0",
        "a is forced to 1 (read by its guard)"]
    assert cli("force", "level", "3", "--api", server)[0] == 0
    fired = eventually(lambda: (w := why(server, "go"))["verdict"] == "blocked"
                       and w["reasons"][0]["text"] == "p: 0 of 1" and w, 10, "go fired")
    assert fired["reasons"][0]["place"] == "p"
    assert ApiClient(server).status()["marking"] == {"q": 1}
