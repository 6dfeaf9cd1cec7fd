"""The debug adapter's pure parts (debug/dapsource.py, dapvars.py, dapwire.py): a line of
the YAML to the transitions of its block (a subnet's line: every instance), the scopes' trees,
the framing's refusals. No socket, no PLC."""

from __future__ import annotations

import io

import pytest

from softplc.debug.dapsource import LineMap, block_end
from softplc.debug.dapvars import marking_vars, symbol_vars, why_vars
from softplc.debug.dapwire import WireError, encode, read_message
from softplc.program.compiler import compile_file
from tests.support import ROOT

PROGRAM = ROOT / "programs" / "transport.yaml"
CONVEYOR = ROOT / "programs" / "nets" / "conveyor.yaml"


@pytest.fixture(scope="module")
def lines() -> LineMap:
    return LineMap.of(compile_file(str(PROGRAM)), PROGRAM)


def test_a_line_maps_to_the_transition_whose_block_holds_it(lines: LineMap) -> None:
    text = PROGRAM.read_text(encoding="utf-8").splitlines()
    first = text.index("  handed_over:") + 1
    for line in range(first, first + 4):  # the key, from, to, when
        block = lines.at(str(PROGRAM), line)
        assert block is not None and block.names == ("handed_over",) and block.first == first
    assert lines.at(str(PROGRAM), first - 1).names == ("hand_over",)  # type: ignore[union-attr]
    assert lines.at(str(PROGRAM), 3) is None  # a comment before the program
    assert lines.at(str(PROGRAM), text.index("transitions:") + 1) is None
    assert lines.where("handed_over") == lines.at(str(PROGRAM), first)
    assert lines.starts(str(PROGRAM)) == sorted(lines.starts(str(PROGRAM)))


def test_a_subnet_line_is_every_instance_of_its_transition(lines: LineMap) -> None:
    text = CONVEYOR.read_text(encoding="utf-8").splitlines()
    start = text.index("  start:") + 1
    block = lines.at(str(ROOT / "programs" / "nets" / ".." / "nets" / "conveyor.yaml"),
                     start + 3)  # `when:`, the path spelt another way
    assert block is not None and block.names == ("c1.start", "c2.start")
    assert lines.where("c2.start") is block


def test_block_end_stops_at_a_line_indented_as_little_as_the_key() -> None:
    yaml = ["transitions:", "  a:", "    from: [p]", "", "    # why", "  b: {from: [q]}",
            "", "places:"]
    assert block_end(yaml, 2) == 5
    assert block_end(yaml, 6) == 6  # a flow mapping on one line; the blank after it is not its


def test_scopes_as_trees() -> None:
    marking = marking_vars({"marking": {"a": 2}, "tokens": {"d": [{"count": 3}]}}, ["a", "b", "d"])
    assert [(v.name, v.value) for v in marking] == [("a", "2"), ("b", "0"), ("d", "0")]
    assert marking[2].children[0].children[0].value == "3"
    scale = {"raw": [0, 100], "eng": [0.0, 1000.0], "unit": "degC"}
    symbols = symbol_vars({"t": {"value": 12.5, "type": "real", "direction": "memory",
                                 "unit": "degC", "scale": scale, "raw": 0x3FA00000},
                           "x": {"value": True, "type": "bool", "raw": 1},
                           "n": {"value": "NaN", "type": "real", "raw": 0x7FC00000}}, {"x": 1})
    assert [(v.name, v.value, v.type) for v in symbols] == [
        ("n", "NaN", "real"), ("t", "12.5 degC", "real memory scaled, degC"),
        ("x", "1 (forced)", "bool")]
    assert [(v.name, c.name, c.value) for v in symbols for c in v.children] == [
        ("n", "raw", "2143289344 (0x7FC00000)"),  # which NaN it is
        ("t", "raw", "1067450368 (0x3FA00000)")]  # 1.25 as a real's bits; none for a bit
    why = why_vars({"verdict": "blocked", "reasons": [{"kind": "tokens", "text": "p: 0 of 1"}],
                    "feeders": [{"transition": "f", "verdict": "blocked",
                                 "reasons": [{"kind": "guard", "text": "guard x is false"}]}]})
    assert [(v.name, v.value) for v in why] == [
        ("verdict", "blocked"), ("1. tokens", "p: 0 of 1"), ("fed by f", "blocked")]
    assert why[2].children[0].value == "guard x is false"


def test_framing_round_trip_and_refusals() -> None:
    stream = io.BytesIO(encode({"seq": 1, "type": "event"}) + encode({"seq": 2}))
    assert read_message(stream) == {"seq": 1, "type": "event"}
    assert read_message(stream) == {"seq": 2}
    assert read_message(stream) is None
    for bad in (b"Content-Length: x\r\n\r\n{}", b"Content-Length: 9\r\n\r\n{}",
                b"Content-Length: 2\r\n\r\n[]", b"X: 1\r\n\r\n{}", b"Content-Length: 2\r\n"):
        with pytest.raises(WireError):
            read_message(io.BytesIO(bad))
