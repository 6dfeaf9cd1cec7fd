"""Regression tests for what the fuzzers found (docs/security.md lists them)."""

from __future__ import annotations

import contextlib
import logging
import socket
import struct
import threading
import time
from pathlib import Path

import pytest

from softplc.core.image import ImageSizes
from softplc.core.problems import ProgramError
from softplc.hmi.server import ModbusSlave
from softplc.program.compiler import compile_text
from tests.fuzz.frames import mbap
from tests.hmi.helpers import ImageSource, connect, request, run_in_thread

ROOT = Path(__file__).resolve().parents[2]
DRILLING = ROOT / "programs" / "drilling.yaml"
# The line of drilling's `io_image:` (the program's header comment may grow).
IO_LINE = next(n for n, x in enumerate(DRILLING.read_text(encoding="utf-8").splitlines(), 1)
               if x.startswith("io_image:"))


def problems(text: str) -> list[str]:
    with pytest.raises(ProgramError) as info:
        compile_text(text, str(DRILLING), ROOT)
    return [str(p) for p in info.value.problems]


def _with_io_image(value: str) -> str:
    text = DRILLING.read_text()
    line = next(x for x in text.splitlines() if x.startswith("io_image:"))
    return text.replace(line, f"io_image: {value}")


@pytest.mark.parametrize("value", ["{a: null}", "[1]", "5", "''"])
def test_an_io_image_that_is_not_a_file_name_is_located(value: str) -> None:
    """Found: `io_image: {a: null}` was reported as FILE "programs/{'a': None}", line 0."""
    found = problems(_with_io_image(value))
    assert found == [f"{DRILLING}:{IO_LINE}: io_image: expected the file name of a symbols file, "
                     f"not {found[0].rsplit('not ', 1)[1]}"]


def test_an_unreadable_io_image_is_located_at_its_reference() -> None:
    """Found: a missing or directory io_image was reported at the target file, line 0."""
    assert problems(_with_io_image("nope.yaml")) == [
        f"{DRILLING}:{IO_LINE}: io_image: 'nope.yaml': cannot read symbols file: No such file or "
        "directory"]


def test_a_control_character_past_the_first_chunk_is_one_located_line() -> None:
    """Found: PyYAML's reader error after 1 KiB came as line 1 plus a second line
    'in "<unicode string>", position N'."""
    text = DRILLING.read_text()
    lines = text.splitlines()
    lines[40] += "\x00"
    assert len("\n".join(lines[:40])) > 1024
    assert problems("\n".join(lines)) == [
        f"{DRILLING}:41: YAML error: character U+0000 is not allowed in YAML"]


def test_a_client_that_resets_with_replies_pending_causes_no_log_flood(
        caplog: pytest.LogCaptureFixture) -> None:
    """Found: after a reset, every buffered request still got a reply written to the dead
    transport, and asyncio logged "socket.send() raised exception." for each: a log flood
    that blocked `softplc run` when its stderr was a pipe."""
    caplog.set_level(logging.WARNING)
    source = ImageSource(ImageSizes())
    burst = b"".join(mbap(bytes.fromhex("030000007d"), i & 0xFFFF, 1) for i in range(20_000))
    slave = ModbusSlave(source, source.sink, sizes=source.image.sizes, port=0)
    with run_in_thread(slave) as handle:
        hog = connect(handle.port, timeout_s=5)
        sender = threading.Thread(target=_send_quietly, args=(hog, burst), daemon=True)
        sender.start()
        time.sleep(0.5)  # the slave has paused: its replies are queued, the client reads none
        hog.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        hog.close()  # RST
        sender.join(5)
        with connect(handle.port) as sock:
            assert request(sock, bytes.fromhex("0400000001")) == bytes.fromhex("04020000")
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING] == []


def _send_quietly(sock: socket.socket, data: bytes) -> None:
    with contextlib.suppress(OSError):  # closed while blocked: that is the point
        sock.sendall(data)


def _laughs(where: str) -> str:
    """A 'billion laughs': 10 ** 9 values behind 9 short anchored lines."""
    lines = ["  a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"  a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 9)]
    return ("program: p\nio_image: ../io_images/transport.yaml\nlol:\n" + "\n".join(lines)
            + f"\nplaces:\n  p: {{{where}: *a8}}\ntransitions: {{}}\n")


@pytest.mark.parametrize("where", ["outputs", "tokens"])
def test_an_alias_bomb_is_refused_at_once(where: str) -> None:
    """Found: `outputs: *a8` made the compiler walk 10**9 values (minutes, in the scan
    process for a download)."""
    started = time.monotonic()
    assert problems(_laughs(where)) == [
        f"{DRILLING}:1: YAML error: more than 100000 values once aliases are expanded"]
    assert time.monotonic() - started < 30  # generous: it takes milliseconds


def test_deep_nesting_is_a_problem_not_a_recursion_error() -> None:
    """Found: `a: [[[[...` 5000 deep raised RecursionError out of compile_text."""
    assert problems("a: " + "[" * 5000 + "]" * 5000) == [
        f"{DRILLING}:1: YAML error: nesting too deep"]


def test_a_nul_character_in_a_subnet_file_name_is_a_located_problem() -> None:
    """make fuzz (scale 50) found: `net: "a\\0b"` raised ValueError from the path resolver."""
    root = Path(__file__).resolve().parents[2]
    text = ('program: p\nio_image: ../io_images/transport.yaml\n'
            'subnets:\n  c1: {net: "nets/con\\0veyor.yaml"}\n')
    try:
        compile_text(text, str(root / "programs" / "p.yaml"), root)
    except ProgramError as exc:
        assert "NUL character" in str(exc) and "p.yaml:4" in str(exc), str(exc)
    else:
        raise AssertionError("a NUL in a file name was accepted")
