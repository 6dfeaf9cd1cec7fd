"""`softplc simulate --script` and `--timeline`: a program that waits for an operator request,
driven without a live HMI; scripts with mistakes are refused with FILE:LINE and a hint."""

from __future__ import annotations

from pathlib import Path

import pytest

from softplc.cli import main
from softplc.core.problems import ProgramError
from softplc.debug.replay import replay
from softplc.program.compiler import compile_file
from softplc.runtime.offline.simscript import load_script
from softplc.runtime.offline.simulate import simulate

ROOT = Path(__file__).resolve().parents[2]
S = 1_000_000_000

IO = """\
symbols:
  request: {address: "%MX0.0", type: bool, description: "HMI: start one cycle"}
  part:    {address: "%IX0.0", type: bool, driver: none}
  busy:    {address: "%QX0.0", type: bool, safe: false, driver: none}
  count:   {address: "%QW0", type: word, driver: none}
"""
# Waits for an operator request while a part is present; acknowledges it by resetting it.
PROGRAM = """\
program: request
io_image: io.yaml
places:
  waiting: {tokens: 1}
  working: {outputs: [busy]}
  done: {coloured: true, tokens: [{n: 0}]}
transitions:
  accept:
    from: [waiting, {place: done, var: d}]
    to: [working, {place: done, token: {n: "d.n + 1"}}]
    when: request and part
    do: ["count = d.n + 1", reset request]
  finish:
    from: [working]
    to: [waiting]
    when: not part
"""
SCRIPT = """\
- at: 1s
  force: {part: true}
- at: 2s
  write: {request: true}
- at: 3s
  release: [part]
"""


@pytest.fixture
def files(tmp_path: Path) -> Path:
    (tmp_path / "io.yaml").write_text(IO, encoding="utf-8")
    (tmp_path / "request.yaml").write_text(PROGRAM, encoding="utf-8")
    (tmp_path / "script.yaml").write_text(SCRIPT, encoding="utf-8")
    return tmp_path


def test_without_a_script_the_program_waits_for_the_request(files: Path) -> None:
    report = simulate(compile_file(files / "request.yaml"), 5 * S)
    assert report["fired"] == {}


def test_a_script_drives_the_request_and_the_timeline_shows_when(files: Path) -> None:
    net = compile_file(files / "request.yaml")
    script = load_script(files / "script.yaml", net.io)
    trace = files / "t.jsonl"
    report = simulate(net, 5 * S, script=script, timeline=True, trace_path=trace)
    assert report["fired"] == {"accept": 1, "finish": 1}
    assert report["outputs_final"] == {"request": 0, "busy": 0, "count": 1}
    assert report["timeline"] == [
        {"k": 100, "t_s": 1.0, "forced": {"part": 1}},
        {"k": 200, "t_s": 2.0, "hmi": ["request=1"], "fired": ["accept"],
         "marking": {"waiting": 0, "working": 1}, "changed": {"busy": 1, "count": 1}},
        {"k": 300, "t_s": 3.0, "forced": {"part": "released"}, "fired": ["finish"],
         "marking": {"waiting": 1, "working": 0}, "changed": {"busy": 0}},
    ]
    assert replay(trace, net).ok  # the trace holds the script's writes and forced inputs


def test_the_cli_prints_the_timeline(files: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["simulate", str(files / "request.yaml"), "--duration", "5s",
                 "--script", str(files / "script.yaml"), "--timeline"]) == 0
    out = capsys.readouterr().out
    assert "fired: {'accept': 1, 'finish': 1}" in out
    assert "k=200     hmi write request=1 | fired accept | marking waiting=0, working=1" in out


def test_hold_written_by_a_script_keeps_the_transport_feed_stopped(tmp_path: Path) -> None:
    (tmp_path / "hold.yaml").write_text("- at: 0s\n  write: {hold: true}\n"
                                        "- at: 30s\n  write: {hold: false}\n", encoding="utf-8")
    net = compile_file(ROOT / "programs" / "transport.yaml")
    script = load_script(tmp_path / "hold.yaml", net.io)
    report = simulate(net, 40 * S, script=script, timeline=True)
    starts = [e for e in report["timeline"] if "c1.start" in e.get("fired", [])]
    assert starts and starts[0]["k"] == 3000  # the part waiting since 1 s goes at 30 s
    held = simulate(net, 29 * S, script=script)
    assert "c1.start" not in held["fired"] and held["plant"]["parts_out"] == 0


BAD_SCRIPT = """\
- at: 1s
  write: {reqest: true}
- at: 2 fortnights
  force: {busy: true}
- at: 3s
  write: {part: true}
  relase: [part]
- write: {count: 70000}
"""


def test_a_bad_script_is_refused_with_located_problems(
        files: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (files / "bad.yaml").write_text(BAD_SCRIPT, encoding="utf-8")
    assert main(["simulate", str(files / "request.yaml"), "--script",
                 str(files / "bad.yaml")]) == 1
    err = capsys.readouterr().err
    bad = files / "bad.yaml"
    assert f"{bad}:2: [0].write.reqest: unknown symbol 'reqest'" in err
    assert "(did you mean 'request'?)" in err
    assert f"{bad}:3: [1].at: bad duration '2 fortnights'" in err
    assert f"{bad}:4: [1].force.busy: busy is out (%QX0.0): force: overrides inputs" in err
    assert f"{bad}:6: [2].write.part: part is an input (%IX0.0)" in err
    assert f"{bad}:7: [2].relase: unknown key 'relase' (did you mean 'release'?)" in err
    assert f"{bad}:8: [3]: missing at:" in err
    assert f"{bad}:8: [3].write.count: symbol count is a word: the value must be a whole " \
           "number 0..65535, not 70000" in err
    assert "Traceback" not in err


def test_a_script_that_is_not_a_list(files: Path) -> None:
    (files / "map.yaml").write_text("at: 1s\n", encoding="utf-8")
    net = compile_file(files / "request.yaml")
    with pytest.raises(ProgramError, match="expected a list of steps"):
        load_script(files / "map.yaml", net.io)
