"""What every GET /status costs the security files: the trusted keys are read again only when
their directory or a key file changed (a key added, removed or written in place shows at the
next request), and an unusable users file is read and logged once per change, not once per
request.

A real service on loopback in front of a real (virtual-time) scan loop; the kernel's inotify
says which files were opened or read (no reader is replaced).
"""

from __future__ import annotations

import ctypes
import logging
import os
import shutil
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from softplc.api.client import ApiClient
from softplc.runtime.loop import LoopConfig
from softplc.security.decide import Authority
from softplc.security.roles import Role
from softplc.security.users import UserStore
from tests.api.conftest import PERIOD_NS, ROOT, Plc, ScanThread, make_server
from tests.api.conftest import plc_parts as plc_parts  # a pytest fixture, reexported

IN_OPEN = 0x20
REQUESTS = 20


class FileReads:
    """Opens of the files in one directory, as inotify reports them (a read needs an open;
    the directory itself, listed, is not counted)."""

    def __init__(self, directory: Path) -> None:
        self._libc = ctypes.CDLL(None, use_errno=True)
        self.fd = self._libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        assert self.fd >= 0, os.strerror(ctypes.get_errno())
        watch = self._libc.inotify_add_watch(self.fd, str(directory).encode(),
                                             IN_OPEN)
        assert watch >= 0, os.strerror(ctypes.get_errno())

    def take(self) -> list[str]:
        """The names of the files opened since the last call."""
        names: list[str] = []
        while True:
            try:
                data = os.read(self.fd, 65536)
            except BlockingIOError:
                return names
            at = 0
            while at < len(data):
                _, _, _, size = struct.unpack_from("iIII", data, at)
                name = data[at + 16:at + 16 + size].rstrip(b"\0").decode()
                if name:
                    names.append(name)
                at += 16 + size

    def close(self) -> None:
        os.close(self.fd)


@pytest.fixture
def service(plc_parts: Plc, tmp_path: Path) -> Iterator[tuple[ApiClient, Path]]:
    state = tmp_path / "state"
    config = LoopConfig(root=str(ROOT), period_ns=PERIOD_NS, state_dir=str(state))
    with ScanThread(plc_parts.channel, plc_parts.writer, plc_parts.board, config), \
            make_server(plc_parts, state) as api:
        yield ApiClient(api.url, state_dir=state, timeout_s=60), state


def _signatures(client: ApiClient) -> dict[str, Any]:
    signatures: dict[str, Any] = client.status()["signatures"]
    return signatures


def test_status_reads_the_trusted_keys_only_when_they_changed(
        service: tuple[ApiClient, Path], keys: Path) -> None:
    client, state = service
    trusted = state / "trusted_keys"
    trusted.mkdir()
    shutil.copy(keys / "alice.pub", trusted)
    reads = FileReads(trusted)
    try:
        assert _signatures(client)["trusted"] == ["alice"]
        assert "alice.pub" in reads.take()  # the first request reads it
        for _ in range(REQUESTS):
            assert _signatures(client)["trusted"] == ["alice"]
        assert reads.take() == [], "an unchanged key read again by GET /status"
        shutil.copy(keys / "bob.pub", trusted)
        assert _signatures(client)["trusted"] == ["alice", "bob"]  # added: the next request
        (trusted / "alice.pub").unlink()
        assert _signatures(client)["trusted"] == ["bob"]  # removed: the next request
        info = trusted.stat()
        (trusted / "bob.pub").write_bytes(b"not a key\n")  # in place, directory stat kept
        os.utime(trusted, ns=(info.st_atime_ns, info.st_mtime_ns))
        seen = _signatures(client)
        assert seen["trusted"] == [] and "no trusted key can be read" in seen["problem"]
        reads.take()
        for _ in range(REQUESTS):
            _signatures(client)
        assert reads.take() == []
    finally:
        reads.close()


def test_an_unusable_users_file_is_read_and_logged_once_per_change(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    store = UserStore(tmp_path)
    authority = Authority(store, lambda: "")
    store.path.write_text("{not json")
    reads = FileReads(tmp_path)
    caplog.set_level(logging.INFO, "softplc.security.decide")
    try:
        for _ in range(REQUESTS):  # what each request of a door with a user's key asks
            assert authority.known() == {}
            assert authority.by_key("op.secret") is None
        assert reads.take().count("users") == 1
        errors = [r for r in caplog.records if r.levelno == logging.ERROR]
        assert len(errors) == 1 and "is unusable" in errors[0].getMessage()
        store.path.unlink()
        store.add("op", Role.OPERATOR, "a-password-1")
        assert set(authority.known()) == {"op"}
        assert set(authority.known()) == {"op"}
        store.path.write_text("[]")  # unusable again, another way: logged again, once
        for _ in range(REQUESTS):
            assert authority.known() == {}
    finally:
        reads.close()
    messages = [r.getMessage() for r in caplog.records]
    assert len([m for m in messages if "is unusable" in m]) == 2, messages
    assert len([m for m in messages if "usable again" in m]) == 1, messages
