"""No YAML is parsed in the scan process while it scans (issue 40.7: why program/yamlfast.py no
longer cuts its regular expressions into pieces, nor program/teardown.py frees a compile's
temporaries piecewise: both let a scan thread of the same process take the interpreter lock
during a compile beside it). A real `softplc run` of the tank with SOFTPLC_COMPILE_LOG (a line
per compile: pid, process name, file): the start program is compiled once, before the scan
process exists (by `softplc run` itself for a small program, runtime/compileproc.compile_start);
an online change, a dry run and a refused download are compiled by a compile process; none by
the scan process."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api.client import ApiClient, ApiError
from tests.support import ROOT, free_port, softplc_run

PROGRAM = ROOT / "programs" / "tank.yaml"


@pytest.fixture
def tank(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[ApiClient, Path]]:
    log, port = tmp_path / "compiles.log", free_port()
    url = f"http://127.0.0.1:{port}"
    monkeypatch.setenv("SOFTPLC_COMPILE_LOG", str(log))  # softplc_run's child inherits it
    with softplc_run([str(PROGRAM), "--plant", "tank", "--start", "--api", f"127.0.0.1:{port}",
                      "--modbus", "off", "--opcua", "off", "--state-dir", str(tmp_path / "state"),
                      "--quiet"],
                     lambda: ApiClient(url, timeout_s=2).status().get("scan_count", 0) > 0):
        yield ApiClient(url, state_dir=tmp_path / "state"), log


def test_the_scan_process_compiles_nothing(tank: tuple[ApiClient, Path]) -> None:
    client, log = tank
    text = PROGRAM.read_text(encoding="utf-8")
    changed = text.replace("duration: 3s", "duration: 4s")
    assert changed != text
    client.download_text(changed, online=True, name="tank.yaml", dry_run=True)
    assert client.download_text(changed, online=True, name="tank.yaml")["ok"]
    with pytest.raises(ApiError):  # refused by the compiler: no place `nowhere`
        client.download_text(text.replace("to: [filling]", "to: [nowhere]"), online=True,
                             name="tank.yaml")
    scan_pid = client.status()["scan_pid"]
    lines = [line.split(" ", 2) for line in log.read_text(encoding="utf-8").splitlines()]
    assert len(lines) >= 4, lines  # the start, the dry run, the change, the refused one
    _start, *downloads = lines
    assert all(name == "softplc-compile" for _, name, _ in downloads), lines
    assert str(scan_pid) not in {pid for pid, _, _ in lines}
