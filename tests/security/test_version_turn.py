"""The program gate's turn and the rule that one signed version names one program (in this
process; tests/security/test_version_race.py races two doors of a real `softplc run`)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from softplc.security import signing, versions
from softplc.security.programgate import ProgramGate, ProgramRefused

BODY = b"places: {p: 1}\n"
OTHER = b"places: {q: 1}\n"


def _line(keys: Path, body: bytes, version: int) -> str:
    return signing.sign(body, signing.load_private(keys / "alice.key"), version)


def test_the_running_version_is_taken_again_only_for_its_own_program(
        keys: Path, gate: ProgramGate) -> None:
    first = _line(keys, BODY, 5)
    gate.applied(BODY, first, gate.admit(BODY, first) or "", False)
    assert gate.admit(BODY, first) == "alice"  # the running program sent again
    other = _line(keys, OTHER, 5)
    with pytest.raises(ProgramRefused, match="version 5 is the running version, of another"):
        gate.admit(OTHER, other)
    assert gate.admit(OTHER, other, allow_older=True) == "alice"  # an engineer's decision
    assert gate.admit(OTHER, _line(keys, OTHER, 6)) == "alice"
    unversioned = signing.sign(OTHER, signing.load_private(keys / "alice.key"))
    with pytest.raises(ProgramRefused, match="older than the running 5"):
        gate.admit(OTHER, unversioned)


def test_unversioned_programs_are_taken_one_after_another(keys: Path, gate: ProgramGate) -> None:
    for body in (BODY, OTHER, BODY):
        line = signing.sign(body, signing.load_private(keys / "alice.key"))
        gate.applied(body, line, gate.admit(body, line) or "", False)
    assert versions.read(gate.state_dir).version == 0


def test_one_turn_at_a_time_and_a_cancelled_wait_holds_nothing(gate: ProgramGate) -> None:
    order: list[str] = []

    async def download(name: str, hold: asyncio.Event | None) -> None:
        async with gate.turn("ed25519 line"):
            order.append(f"{name} in")
            if hold is not None:
                await hold.wait()
            order.append(f"{name} out")

    async def body() -> None:
        hold = asyncio.Event()
        first = asyncio.create_task(download("a", hold))
        await asyncio.sleep(0.05)
        cancelled = asyncio.create_task(download("c", None))
        second = asyncio.create_task(download("b", None))
        await asyncio.sleep(0.1)
        assert order == ["a in"]  # both wait for the turn
        cancelled.cancel()
        hold.set()
        await asyncio.gather(first, second)
        async with gate.turn(None):  # no signature, no turn: never waits
            order.append("unsigned")

    asyncio.run(body())
    assert order == ["a in", "a out", "b in", "b out", "unsigned"]
