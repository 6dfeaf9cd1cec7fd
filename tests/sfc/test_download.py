"""A chart goes to a real `softplc run` as a program does: `softplc download CHART.xml` packs
the XML (and its FILE.io.yml), the server compiles it and runs it; an unsafe chart is refused
by the client's check before anything is sent, naming the step."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

from softplc.program.bundle import from_files
from tests.runtime.test_workflow import answers, settled, softplc
from tests.sfc.chartxml import ChartSpec, chart_xml
from tests.support import free_port, softplc_run

EXAMPLES = Path(__file__).parent / "examples"
ROOT = Path(__file__).parents[2]


@pytest.fixture
def server(tmp_path: Path) -> Iterator[str]:
    where = tmp_path / "server"
    where.mkdir()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run(["--api", f"127.0.0.1:{port}", "--modbus", f"127.0.0.1:{free_port()}",
                      "--opcua", "off", "--state-dir", "state", "--quiet", "--period", "10ms"],
                     lambda: answers(url), cwd=where):
        yield url


def test_a_chart_bundle_carries_its_drivers_file() -> None:
    bundle = from_files(ROOT / "programs/drilling_sfc.xml")
    assert (bundle.program, sorted(bundle.files)) == \
        ("drilling_sfc.xml", ["drilling_sfc.io.yml", "drilling_sfc.xml"])


def test_a_chart_is_downloaded_and_runs_and_an_unsafe_one_is_refused(
        server: str, tmp_path: Path) -> None:
    desk = tmp_path / "desk"
    desk.mkdir()
    shutil.copy(EXAMPLES / "codesys_press.xml", desk / "press.xml")
    down = softplc("download", "press.xml", "--api", server, cwd=desk)
    assert down.returncode == 0, down.stderr
    assert softplc("start", "--api", server, cwd=desk).returncode == 0
    status = settled(server)
    assert status["program"] == "Press"
    assert status["marking"] == {"Init": 1}
    unsafe = ChartSpec(["Start", "Left", "Right", "Joined"], ["Start"], [
        (["Start"], ["Left", "Right"], "go"), (["Left"], ["Start"], "go"),
        (["Left", "Right"], ["Joined"], "go"), (["Joined"], ["Start"], "TRUE")],
        variables={"go": ("BOOL", "%IX0.0")})
    (desk / "unsafe.xml").write_text(chart_xml(unsafe), encoding="utf-8")
    refused = softplc("download", "unsafe.xml", "--api", server, cwd=desk)
    assert refused.returncode != 0
    assert "unsafe chart: step Right is activated while it is active" in refused.stderr
    assert settled(server)["program"] == "Press"


def test_a_pou_of_a_file_with_several_is_run_and_downloaded_as_file_xml_hash_pou(
        tmp_path: Path) -> None:
    one = chart_xml(ChartSpec(["Start", "Run"], ["Start"], [
        (["Start"], ["Run"], "go"), (["Run"], ["Start"], "NOT go")],
        variables={"go": ("BOOL", "%IX0.0")}))
    pou = one[one.index("<pou "):one.index("</pou>") + 6]
    (tmp_path / "two.xml").write_text(one.replace(
        "</pous>", pou.replace('name="Chart"', 'name="Other"') + "</pous>"), encoding="utf-8")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with softplc_run(["two.xml#Other", "--api", f"127.0.0.1:{port}", "--modbus",
                      f"127.0.0.1:{free_port()}", "--opcua", "off", "--state-dir", "state",
                      "--quiet", "--period", "10ms"], lambda: answers(url), cwd=tmp_path):
        assert settled(url)["program"] == "Other"
        down = softplc("download", "two.xml#Chart", "--api", url, cwd=tmp_path)
        assert down.returncode == 0, down.stderr
        assert softplc("start", "--api", url, cwd=tmp_path).returncode == 0
        assert settled(url)["program"] == "Chart"
        back = softplc("upload", "-o", "up", "--api", url, cwd=tmp_path)
        assert back.returncode == 0, back.stderr
        assert (tmp_path / "up/two.xml").read_bytes() == (tmp_path / "two.xml").read_bytes()
