"""The program workflow (issue 16) with a real server process: a program in a nested folder with its
own io image and subnets passes `check`, is downloaded as a bundle to a `softplc run`
started in another directory, runs, is shown before an online change (`--dry-run`), and
`softplc upload` gets it back byte for byte."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.api.client import ApiClient, ApiError
from softplc.cli import main
from tests.support import eventually, free_port, softplc_run

ROOT = Path(__file__).resolve().parents[2]
FILES = ("deep/sub/c.yaml", "deep/nets/conveyor.yaml", "io/transport.yaml")


def softplc(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """A `softplc` command, run in this process in `cwd` (the console script's main(): a
    process start per command would cost seconds on a loaded machine, the server is the
    real process under test)."""
    out, err = io.StringIO(), io.StringIO()
    here = os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(list(args))
    finally:
        os.chdir(here)
    return subprocess.CompletedProcess(["softplc", *args], code, out.getvalue(), err.getvalue())


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """The transport program moved into deep/sub/ with its io image two levels up and its
    subnet beside: paths no server-side programs directory could resolve."""
    desk = tmp_path / "desk"
    (desk / "deep/sub").mkdir(parents=True)
    (desk / "deep/nets").mkdir()
    (desk / "io").mkdir()
    text = (ROOT / "programs/transport.yaml").read_text(encoding="utf-8")
    text = text.replace("io_image: ../io_images/transport.yaml",
                        "io_image: ../../io/transport.yaml")
    text = text.replace("net: nets/conveyor.yaml", "net: ../nets/conveyor.yaml")
    (desk / "deep/sub/c.yaml").write_text(text, encoding="utf-8")
    shutil.copy(ROOT / "programs/nets/conveyor.yaml", desk / "deep/nets/conveyor.yaml")
    shutil.copy(ROOT / "io_images/transport.yaml", desk / "io/transport.yaml")
    return desk


@pytest.fixture
def server(tmp_path: Path) -> Iterator[str]:
    """`softplc run` without a program, in a directory of its own."""
    where = tmp_path / "server"
    where.mkdir()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run(["--api", f"127.0.0.1:{port}", "--modbus", f"127.0.0.1:{free_port()}",
                      "--opcua", "off", "--state-dir", "state", "--quiet", "--period", "10ms"],
                     lambda: answers(url), cwd=where):
        yield url


def answers(url: str) -> bool:
    try:
        ApiClient(url, timeout_s=2).status()
    except (ApiError, OSError):
        return False
    return True


def status(url: str, cwd: Path) -> dict[str, object]:
    done = softplc("status", "--api", url, "--json", cwd=cwd)
    assert done.returncode == 0, done.stderr
    answer: dict[str, object] = json.loads(done.stdout)
    return answer


def settled(url: str) -> dict[str, object]:
    """The status once the board (marking, program) is newer than what has been answered so
    far: the snapshot's scan count follows every scan, the board every ~50 ms."""
    client = ApiClient(url, timeout_s=5)
    now = int(client.status()["scan_count"])
    answer: dict[str, object] = eventually(
        lambda: (s := client.status())["board_scan_count"] > now and s, 10, "a newer board")
    return answer


def test_a_nested_program_goes_to_a_remote_plc_runs_and_comes_back_byte_for_byte(
        project: Path, server: str, tmp_path: Path) -> None:
    checked = softplc("check", "deep/sub/c.yaml", cwd=project)
    assert checked.returncode == 0, checked.stderr
    down = softplc("download", "deep/sub/c.yaml", "--online", "--api", server, cwd=project)
    assert down.returncode == 0, down.stderr
    started = softplc("start", "--api", server, cwd=project)
    assert started.returncode == 0, started.stderr
    settled(server)
    first = status(server, project)
    assert first["state"] == "RUNNING" and first["program"] == "transport"
    eventually(lambda: int(status(server, project)["scan_count"])  # type: ignore[call-overload]
               > int(first["scan_count"]), 10, "it scans")  # type: ignore[call-overload]

    out = tmp_path / "back"
    up = softplc("upload", "-o", str(out), "--api", server, cwd=project)
    assert up.returncode == 0, up.stderr
    back = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert back == sorted(FILES)
    for name in FILES:
        assert (out / name).read_bytes() == (project / name).read_bytes(), name


def test_dry_run_shows_the_plan_and_applies_nothing(project: Path, server: str) -> None:
    assert softplc("download", "deep/sub/c.yaml", "--api", server, cwd=project).returncode == 0
    assert softplc("start", "--api", server, cwd=project).returncode == 0
    before = settled(server)
    changed = (project / "deep/sub/c.yaml").read_text(encoding="utf-8").replace(
        "places:\n", "places:\n  spare: {tokens: 2}\n", 1)
    (project / "deep/sub/c.yaml").write_text(changed, encoding="utf-8")
    dry = softplc("download", "deep/sub/c.yaml", "--online", "--dry-run", "--api", server,
                  cwd=project)
    assert dry.returncode == 0, dry.stderr
    out = dry.stdout
    assert "new places (start with their declared tokens):\n  spare" in out
    assert "c1.idle" in out and "would be ACCEPTED" in out
    assert '{"count": 0}' in out  # the coloured place's record
    after = settled(server)
    assert after["program_hash"] == before["program_hash"]  # nothing applied
    assert "spare" not in after["marking"]  # type: ignore[operator]

    applied = softplc("download", "deep/sub/c.yaml", "--online", "--api", server, cwd=project)
    assert applied.returncode == 0, applied.stderr
    assert settled(server)["marking"]["spare"] == 2  # type: ignore[index]


def test_another_program_needs_replace_and_the_dry_run_says_so(
        project: Path, server: str) -> None:
    assert softplc("download", "deep/sub/c.yaml", "--api", server, cwd=project).returncode == 0
    assert softplc("start", "--api", server, cwd=project).returncode == 0
    other = project / "deep/sub/other.yaml"
    other.write_text((project / "deep/sub/c.yaml").read_text(encoding="utf-8").replace(
        "program: transport", "program: other"), encoding="utf-8")
    dry = softplc("download", str(other), "--online", "--dry-run", "--api", server, cwd=project)
    assert dry.returncode == 1 and "would be REFUSED" in dry.stdout and "--replace" in dry.stdout
    refused = softplc("download", str(other), "--online", "--api", server, cwd=project)
    assert refused.returncode == 1 and "--replace" in refused.stderr
    assert settled(server)["program"] == "transport"
    replaced = softplc("download", str(other), "--online", "--replace", "--api", server,
                       cwd=project)
    assert replaced.returncode == 0, replaced.stderr
    assert settled(server)["program"] == "other"
