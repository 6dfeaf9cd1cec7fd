"""The boot program file (program/boot.py) is written a piece at a time, so that the download
thread never holds the interpreter lock for long while the scan runs; the file is the same JSON
as one json.dumps of the whole, whatever characters fall on a piece's edge."""

from __future__ import annotations

import base64
import json
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from softplc.program import boot

EDGE = boot._PIECE  # a piece's size in characters (text) and about in bytes (bundle)


def _reference(program: boot.BootProgram) -> dict[str, object]:
    """What the file held when it was written in one json.dumps."""
    return json.loads(json.dumps({
        "format": boot.FORMAT, "filename": program.filename, "root": program.root,
        "text": program.text, "program_hash": program.program_hash,
        "bundle": None if program.bundle is None else base64.b64encode(program.bundle).decode()}))


@settings(max_examples=25, deadline=None)
@given(tail=st.text(min_size=1, max_size=40), cut=st.integers(0, 5),
       bundle=st.none() | st.binary(min_size=0, max_size=200),
       root=st.none() | st.text(max_size=10))
def test_the_file_is_the_json_of_the_whole_program(
        tail: str, cut: int, bundle: bytes | None, root: str | None) -> None:
    text = "a" * (EDGE - cut) + tail + '"\\\n\u00e9\U0001F600' + "b" * EDGE
    packed = None if bundle is None else bundle + bytes(range(256)) * (EDGE // 128)
    program = boot.BootProgram("dl.yaml", text, root, packed, "abc")
    written = b"".join(boot._json_pieces(program))
    assert json.loads(written) == _reference(program)


def test_a_staged_program_loads_back_byte_for_byte(tmp_path: Path) -> None:
    text = ("x: 1  # é\n" * (3 * EDGE // 10)) + "\U0001F600"
    packed = bytes(range(256)) * (EDGE // 64 + 1)
    program = boot.BootProgram(str(tmp_path / "p.yaml"), text, str(tmp_path), packed, "h1")
    boot.commit(boot.stage(tmp_path, program))
    assert boot.load(tmp_path) == program
    pieces = list(boot._json_pieces(program))
    assert len(pieces) > 4 and max(map(len, pieces)) <= 2 * EDGE  # no one stretch for it all
