"""The operator's page in a real headless Chromium (Debian's chromium + chromium-driver,
driven by selenium) against a real `softplc run` on the simulated plant, loopback only:
no console error, each case study's net drawn with its places and transitions, tokens move,
stop/start show, forcing an input changes what the program does and shows as forced, a
download with a syntax error shows its line. Screenshots go to a tmp dir (test artefacts);
SOFTPLC_WEB_SHOTS=DIR copies them there (docs/web-transport.png comes from that).
"""

from __future__ import annotations

import ctypes
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import pytest

from softplc.api.client import ApiClient
from tests.support import free_port

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None or DRIVER is None,
    reason="needs Debian's chromium and chromium-driver (.ci/run installs them)")
webdriver = pytest.importorskip("selenium.webdriver", reason="needs selenium (dev extra)")
T = TypeVar("T")


def until(probe: Callable[[], T], timeout_s: float = 10.0, what: str = "condition",
          show: Callable[[], object] | None = None) -> T:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            result = probe()
        except Exception:
            result = None  # type: ignore[assignment]
        if result:
            return result
        if time.monotonic() > deadline:
            seen = f" (shown: {show()})" if show is not None else ""
            raise AssertionError(f"{what}: not within {timeout_s} s{seen}")
        time.sleep(0.1)


PRCTL = ctypes.CDLL(None).prctl  # looked up here: the forked child only calls it


def die_with_parent() -> None:
    """In the child before exec: SIGTERM when the test process dies (a pytest killed mid-run
    must not leave a `softplc run` serving forever; Linux prctl PR_SET_PDEATHSIG = 1)."""
    PRCTL(1, signal.SIGTERM)


class Softplc:
    """`softplc run PROGRAM --start` with its API on a free loopback port."""

    def __init__(self, program: str, state: Path, start: bool = True) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "softplc.cli", "run", program, *(["--start"] if start else []),
             "--modbus", "off",
             "--opcua", "off", "--api", f"127.0.0.1:{self.port}", "--state-dir", str(state),
             "--quiet", "--period", "10ms"], cwd=ROOT, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, preexec_fn=die_with_parent)
        self.client = ApiClient(self.url, timeout_s=10)
        state_name = "RUNNING" if start else "STOPPED"
        until(lambda: self.client.status()["state"] == state_name, 60,
              f"softplc run is {state_name}")

    def close(self) -> None:
        self.proc.send_signal(signal.SIGINT)
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1500,1100", "--no-first-run", "--disable-extensions"):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = webdriver.ChromeService(executable_path=DRIVER)
    driver = webdriver.Chrome(options=options, service=service)
    driver.set_page_load_timeout(20)
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def shots(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("screenshots")


def errors(driver: Any, expected: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """SEVERE console entries, less the HTTP refusals the test provoked on purpose (Chromium
    logs every 4xx answer as a network error)."""
    return [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"
            and not (e.get("source") == "network" and any(x in e["message"] for x in expected))]


def js(driver: Any, script: str) -> Any:
    return driver.execute_script(script)


def open_page(driver: Any, plc: Softplc) -> None:
    driver.get_log("browser")  # what an earlier page logged is not this page's
    driver.get(plc.url + "/")
    until(lambda: js(driver, "return window.softplc && window.softplc.cy !== null "
                             "&& window.softplc.frames > 2"), 15, "the page draws the net")


def give_key(driver: Any, key: str) -> None:
    """Type `key` into the page's key dialog once a refused action has opened it."""
    until(lambda: js(driver, "return document.getElementById('token-dialog').open"), 15,
          "the page asks for a key")
    driver.find_element("id", "token").send_keys(key)
    driver.find_element("css selector", "#token-form button").click()
    until(lambda: not js(driver, "return document.getElementById('token-dialog').open"), 5,
          "the key dialog closes")


def counts(driver: Any) -> dict[str, int]:
    result: dict[str, int] = js(driver, "return {places: softplc.cy.nodes('.place').length, "
                                        "transitions: softplc.cy.nodes('.trans').length, "
                                        "instances: softplc.cy.nodes('.instance').length}")
    return result


def marking(driver: Any) -> dict[str, int]:
    result: dict[str, int] = js(driver, "return softplc.lastFrame.marking")
    return result


def save(driver: Any, shots: Path, name: str) -> Path:
    path = shots / name
    driver.save_screenshot(str(path))
    copy_to = os.environ.get("SOFTPLC_WEB_SHOTS")
    if copy_to:
        shutil.copy(path, Path(copy_to) / name)
    return path


def fired(driver: Any, name: str) -> int:
    return int(js(driver, f"return softplc.lastFrame.net_live.fired_counts[{name!r}] || 0"))


def fired_api(plc: Softplc, name: str) -> int:
    live = plc.client.status().get("net_live") or {}
    return int((live.get("fired_counts") or {}).get(name, 0))


def test_transport_page_live_forcing_and_program_handling(
        browser: Any, shots: Path, tmp_path: Path) -> None:
    plc = Softplc("programs/transport.yaml", tmp_path / "state", start=False)
    try:
        # m1 forced off before the program runs (a start keeps forces; only a reset drops
        # them): the first part, put at s1_i at 1 s, is taken on by c1.start but the belt
        # stands still, so it never reaches s1_o by itself. c1.arrive can then only fire
        # because the page forces s1_o, however slowly this machine runs the test.
        plc.client.force("m1", 0)
        plc.client.start()
        until(lambda: plc.client.status()["marking"].get("c1.moving"), 30, "c1 took a part on")
        assert fired_api(plc, "c1.arrive") == 0 and plc.client.read_symbol("s1_o") is False
        open_page(browser, plc)
        assert counts(browser) == {"places": 8, "transitions": 7, "instances": 2}
        assert browser.find_element("id", "program").text == "transport"
        assert browser.find_element("id", "state").text == "RUNNING"
        rows = browser.find_elements("css selector", "#image tbody tr")
        assert len(rows) == len(plc.client.symbols())
        # Forcing an input from the page: forced s1_o = 1 makes c1.arrive fire.
        row = browser.find_element("css selector", '#image tr[data-symbol="s1_o"]')
        assert fired(browser, "c1.arrive") == 0 and marking(browser).get("c1.moving") == 1
        row.find_element("css selector", "input.force").send_keys("1")
        row.find_element("css selector", "button.force").click()
        # Without credentials the page only reads: the refused force asks for a key, and
        # the engineer gives the owner's (STATE_DIR/api_token), as a person would.
        give_key(browser, (tmp_path / "state" / "api_token").read_text().strip())
        row.find_element("css selector", "input.force").clear()
        row.find_element("css selector", "input.force").send_keys("1")
        row.find_element("css selector", "button.force").click()
        until(lambda: "forced" in row.get_attribute("class"), 15, "the row is marked forced",
              show=lambda: browser.find_element("id", "message").text)
        assert row.find_element("css selector", "td.value").text.startswith("1")
        until(lambda: browser.find_element("id", "forced-count").text == "2 forced", 15)
        until(lambda: fired(browser, "c1.arrive"), 15, "c1.arrive fires on the force")
        assert fired_api(plc, "c1.arrive") == 1  # once: the part is still where it was
        plc.client.unforce("m1")  # the belt may run again
        until(lambda: marking(browser).get("c1.full") or marking(browser).get("handing_over"),
              5, "the part is taken as arrived")
        # Tokens move while the PLC scans and the page draws the marking it receives.
        first = marking(browser)
        until(lambda: marking(browser) != first, 20, "the marking shown changes")
        drawn = js(browser, "return softplc.cy.nodes('.place.marked').map(n => n.data('name'))")
        shown = marking(browser)
        marked = sorted(p for p, n in shown.items() if n)
        assert sorted(drawn) == marked or marking(browser) != shown
        assert plc.client.status()["forced"] == {"s1_o": 1}
        save(browser, shots, "web-transport.png")
        browser.find_element("id", "release-all").click()
        until(lambda: "forced" not in row.get_attribute("class"), 15, "released")
        assert plc.client.forces() == {}

        # Stop and resume change the state shown; a refused command shows its reason.
        browser.find_element("css selector", 'button[data-command="stop"]').click()
        until(lambda: browser.find_element("id", "state").text == "STOPPED", 15)
        browser.find_element("css selector", 'button[data-command="stop"]').click()
        until(lambda: "stop refused: stop is not accepted in state STOPPED"
              in browser.find_element("id", "message").text, 15, "the refusal is shown")
        browser.find_element("css selector", 'button[data-command="resume"]').click()
        until(lambda: browser.find_element("id", "state").text == "RUNNING", 15)

        # A download with a syntax error shows every problem at its file:line.
        bad = tmp_path / "broken.yaml"
        bad.write_text("program: broken\nio_image: ../io_images/transport.yaml\n"
                       "places:\n  p: {tokens: 1\n", encoding="utf-8")
        browser.find_element("id", "program-file").send_keys(str(bad))
        browser.find_element("id", "download").click()
        problems = until(lambda: browser.find_elements("css selector", "#problems li"), 10,
                         "the download's problems are listed")
        texts = [p.text for p in problems]
        assert any("broken.yaml:5: YAML syntax error" in t for t in texts), texts
        assert browser.find_element("id", "state").text == "RUNNING"  # nothing changed
        assert errors(browser, ("/api/v1/forces/s1_o - Failed to load resource: the server "
                                "responded with a status of 401",  # before the key was given
                                "/api/v1/stop - Failed to load resource: the server responded "
                                "with a status of 409", "/api/v1/program?name=broken.yaml - "
                                "Failed to load resource: the server responded with a status "
                                "of 422")) == []
    finally:
        browser.get("about:blank")  # no page left reconnecting to a stopped softplc
        plc.close()


def test_drilling_page_draws_its_net(browser: Any, shots: Path, tmp_path: Path) -> None:
    plc = Softplc("programs/drilling.yaml", tmp_path / "state")
    try:
        open_page(browser, plc)
        assert counts(browser) == {"places": 8, "transitions": 7, "instances": 0}
        assert browser.find_element("id", "program").text == "drilling"
        # Coloured token data on hover comes from the frames: the counter place's record. The
        # drill's firing holds the counter's token for its 2 s (three-phase: the place is empty
        # meanwhile), so the record is awaited for one drilling cycle, not read at once.
        until(lambda: js(browser, "const t = softplc.lastFrame.net_live.tokens.counter;"
                                  "return t !== undefined && t.length === 1 "
                                  "&& 'drilled' in t[0]"), 30, "the counter's token record")
        until(lambda: js(browser, "return softplc.series[0].length") > 3, 15, "the plot fills")
        save(browser, shots, "web-drilling.png")
        assert errors(browser) == []
    finally:
        browser.get("about:blank")  # no page left reconnecting to a stopped softplc
        plc.close()


# Injected before the page's own scripts (Chromium's Page.addScriptToEvaluateOnNewDocument):
# count every Cytoscape instance the page creates (the vendored library is wrapped as it
# loads), and make /api/v1/net slow (`delay_ms`) and unavailable (a 503 like a busy status
# board's) until the page has had `fail_frames` frames, the conditions of a loaded machine.
HOOK = r"""
(() => {
  const cfg = %s;
  window.__builds = 0;
  window.__netAsked = 0;
  let real;
  Object.defineProperty(window, "cytoscape", { configurable: true, get() { return real; },
    set(lib) { real = new Proxy(lib, { apply(target, self, args) {
      if (args.length === 1 && typeof args[0] === "object") window.__builds += 1;
      return Reflect.apply(target, self, args); } }); } });
  const realFetch = window.fetch.bind(window);
  window.fetch = async (url, init) => {
    if (String(url).endsWith("/api/v1/net")) {
      window.__netAsked += 1;
      await new Promise((resolve) => setTimeout(resolve, cfg.delay_ms));
      if (!window.softplc || window.softplc.frames < cfg.fail_frames) {
        return new Response('{"error": "status board unavailable: test", "problems": []}',
                            { status: 503, headers: { "Content-Type": "application/json" } });
      }
    }
    return realFetch(url, init);
  };
})();
"""


def open_hooked(driver: Any, plc: Softplc, delay_ms: int, fail_frames: int) -> None:
    """Load the page with HOOK, and wait until it has drawn the net and filled the image."""
    source = HOOK % f'{{"delay_ms": {delay_ms}, "fail_frames": {fail_frames}}}'
    hook = driver.execute_cdp_cmd("Page.addScriptToEvaluateOnNewDocument", {"source": source})
    try:
        driver.get_log("browser")
        driver.get(plc.url + "/")
    finally:
        driver.execute_cdp_cmd("Page.removeScriptToEvaluateOnNewDocument",
                               {"identifier": hook["identifier"]})
    until(lambda: js(driver, "return softplc.cy !== null && softplc.cy.nodes('.place').length "
                             "&& document.querySelectorAll('#image tbody tr').length"),
          15, "the page draws the net and the image")


def frames_pass(driver: Any, n: int) -> None:
    """Wait until the page has received `n` more frames (each could trigger a rebuild)."""
    start = js(driver, "return softplc.frames")
    until(lambda: js(driver, "return softplc.frames") >= start + n, 15, f"{n} more frames")


def builds(driver: Any) -> tuple[int, int]:
    """Nets built: Cytoscape instances counted by HOOK, and the page's own count."""
    return js(driver, "return window.__builds"), js(driver, "return softplc.netBuilds")


def test_the_page_builds_its_net_once_per_program_and_never_leaves_it_empty(
        browser: Any, tmp_path: Path) -> None:
    plc = Softplc("programs/transport.yaml", tmp_path / "state")
    symbols = len(plc.client.symbols())
    try:
        # A slow /net: ~20 frames arrive while it is asked; one fetch, one net.
        open_hooked(browser, plc, delay_ms=800, fail_frames=0)
        frames_pass(browser, 25)
        assert builds(browser) == (1, 1) and js(browser, "return window.__netAsked") == 1
        assert counts(browser)["places"] == 8
        assert len(browser.find_elements("css selector", "#image tbody tr")) == symbols

        # /net unavailable for the first 10 frames: the page keeps asking, then draws both.
        open_hooked(browser, plc, delay_ms=50, fail_frames=10)
        assert js(browser, "return window.__netAsked") > 1  # the 503s were really seen
        frames_pass(browser, 25)
        assert builds(browser) == (1, 1) and counts(browser)["places"] == 8
        assert len(browser.find_elements("css selector", "#image tbody tr")) == symbols

        # A program change (online, one place more): exactly one more build, of the new net.
        text = (ROOT / "programs/transport.yaml").read_text(encoding="utf-8")
        changed = text.replace("places:\n", "places:\n  spare: {}\n", 1)
        assert plc.client.download(changed, online=True, name="transport.yaml")["ok"]
        until(lambda: counts(browser)["places"] == 9, 15, "the new net is drawn")
        frames_pass(browser, 25)
        assert builds(browser) == (2, 2) and counts(browser)["places"] == 9
        assert errors(browser) == []
    finally:
        browser.get("about:blank")  # no page left reconnecting to a stopped softplc
        plc.close()
