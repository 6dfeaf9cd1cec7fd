"""A compile reply through a file (runtime/replyfile.py): a large net's pieces come back as
views into the one buffer read, not copied into new objects while the download thread holds
the interpreter lock (issue 40 item 8), and load into the same net; small replies and
refusals travel inline; the file is gone once read."""

from __future__ import annotations

import os
import pickle
from pathlib import Path

import pytest

from softplc.bench.onlinebench import ring_program
from softplc.core.net import CompiledNet
from softplc.core.problems import Problem, ProgramError
from softplc.program import wire
from softplc.program.compiler import compile_text
from softplc.runtime.prepare import Built
from softplc.runtime.replyfile import BY_FILE_BYTES, pack, unpack

ROOT = Path(__file__).resolve().parents[2]


def _net(transitions: int) -> CompiledNet:
    return compile_text(ring_program(transitions, 1), str(ROOT / "programs" / "ring.yaml"), ROOT)


def test_a_large_net_comes_back_as_views_into_one_buffer_and_loads_equal(
        tmp_path: Path) -> None:
    net = _net(2000)
    pieces = wire.dumps(net)
    assert sum(map(len, pieces)) > BY_FILE_BYTES
    message = pack(("ok", Built(pieces, {"summary": "s", "findings": []}, ("/b",))),
                   str(tmp_path))
    assert len(message) < 200  # a file's name, not the reply
    (path,) = tmp_path.iterdir()
    assert path.name.startswith(f"softplc_{os.getpid()}_reply_")  # as leftovers.py removes
    assert path.stat().st_mode & 0o077 == 0  # this user's only
    kind, built = unpack(message)
    assert list(tmp_path.iterdir()) == []  # read once, removed
    assert kind == "ok" and isinstance(built, Built)
    assert built.analysis == {"summary": "s", "findings": []} and built.bundle_roots == ("/b",)
    assert all(isinstance(p, memoryview) for p in built.net)
    assert len({id(p.obj) for p in built.net if isinstance(p, memoryview)}) == 1  # one buffer
    assert [bytes(p) for p in built.net] == list(pieces)
    loaded = wire.loads(built.net)
    assert loaded.program_hash == net.program_hash
    assert loaded.place_names == net.place_names
    assert [t.name for t in loaded.transitions] == [t.name for t in net.transitions]


def test_small_replies_and_refusals_travel_inline(tmp_path: Path) -> None:
    refusal = ProgramError([Problem("ring.yaml", 3, "places", "bad")])
    kind, value = unpack(pack(("error", refusal), str(tmp_path)))
    assert kind == "error" and isinstance(value, ProgramError)
    assert str(value) == str(refusal)
    small = wire.dumps(_net(3))
    kind, built = unpack(pack(("ok", Built(small, None)), str(tmp_path)))
    assert built.net == small and list(tmp_path.iterdir()) == []


def test_a_file_that_is_not_a_reply_is_refused(tmp_path: Path) -> None:
    stray = tmp_path / "softplc_1_reply_x"
    stray.write_bytes(b"\0" * 64)
    with pytest.raises(ValueError, match="not a compile reply"):
        unpack(pickle.dumps(("file", str(stray))))
    assert not stray.exists()
