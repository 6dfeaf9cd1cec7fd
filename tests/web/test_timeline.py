"""The page's recent past (softplc/api/static/timeline.js, docs/web.md) in a real headless
Chromium against a real `softplc run` of the transport program: a timing diagram of s1_i, m1
and the marking of c1.moving chosen from the page, a pinned symbol in the watch list,
scrubbing back 100 scans shows that scan's image, marking and what fired, and "why" at a past
scan points to the trace while at the newest scan it asks the PLC. Started and authenticated
as tests/web/test_browser.py does (loopback: the page reads as a viewer)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tests.web import test_browser
from tests.web.test_browser import Softplc, errors, js, open_page, save, until

pytestmark = test_browser.pytestmark  # the same skip: no chromium, no test
browser = test_browser.browser  # the module's browser and screenshot fixtures
shots = test_browser.shots

SIGNALS = ("s1_i", "m1", "c1.moving")


def add(driver: Any, name: str, button: str) -> None:
    driver.find_element("id", "tl-name").send_keys(name)
    driver.find_element("id", button).click()


def data(driver: Any, script: str) -> Any:
    return js(driver, "const d = softplc.timeline.data; " + script)


def test_timing_diagram_watch_list_and_scrubbing(
        browser: Any, shots: Path, tmp_path: Path) -> None:
    plc = Softplc("programs/transport.yaml", tmp_path / "state")
    try:
        open_page(browser, plc)
        for name in SIGNALS:
            add(browser, name, "tl-plot")
        add(browser, "s1_i", "tl-pin")
        assert js(browser, "return softplc.timeline.signals") == list(SIGNALS)
        # Over 100 scans in the window, and the chart's lanes are the three signals.
        until(lambda: data(browser, "return d && d.scans.length") > 150, 30,
              "the window holds more than 150 scans")
        assert js(browser, "return softplc.timeline.plot.series.slice(1).map(s => s.label)") \
            == list(SIGNALS)
        assert data(browser, "return d.values.s1_i.every(v => typeof v === 'boolean')")
        assert data(browser, "return d.values.m1.length === d.scans.length")
        # c1.moving, a place: 0 or 1 tokens at each scan from the board samples (1 marking
        # as the part moves; the diagram holds the last sample's value).
        # In one call: a poll merges new samples and redraws in one task of the page, so one
        # script sees both as one (two calls saw 173 points against 178 scans in a CI run).
        moving, scans = data(browser, "return [softplc.timeline.plot.data[3], d.scans.length]")
        assert len(moving) == scans
        assert {round(v % 1.4, 6) for v in moving if v is not None} <= {0.0, 1.0}
        # Read in one call: the live page rebuilds the watch rows as samples come (an element
        # found, then read, went stale in a CI run beside 4 busy loops).
        watch = js(browser, "return [...document.querySelectorAll('#tl-watch tbody tr')]"
                            ".map(r => r.getAttribute('data-name'))")
        assert watch == ["s1_i"]
        save(browser, shots, "web-timeline.png")

        # Scrub back 100 scans: the slider, then what the page shows for that scan.
        js(browser, "const s = document.getElementById('tl-slider');"
                    "s.value = String(Number(s.max) - 100);"
                    "s.dispatchEvent(new Event('input'));")
        index = js(browser, "return softplc.timeline.index")
        scan = data(browser, f"return d.scans[{index}]")
        assert js(browser, "return softplc.timeline.paused") is True
        # The newest of the same window (read before the scrub, a refresh in between could
        # drop old samples from its front and shift every index: seen beside 4 busy loops).
        newest = data(browser, "return d.scans[d.scans.length - 1]")
        assert scan <= newest - 100  # 100 samples back: at least 100 scans back
        at = browser.find_element("id", "tl-at")
        assert at.get_attribute("data-scan") == str(scan) and f"scan {scan}" in at.text
        assert "100 samples back" in at.text
        image = {r.get_attribute("data-name"): r.find_elements("tag name", "td")[1].text
                 for r in browser.find_elements("css selector", "#tl-image tbody tr")}
        expected = data(browser, f"return Object.fromEntries(Object.entries(d.values)"
                                 f".map(([k, v]) => [k, v[{index}]]))")
        assert image == {k: ("1" if v is True else "0" if v is False else str(v))
                         for k, v in expected.items()}
        assert browser.find_element("id", "tl-fired").text.startswith("marking of the board")
        marked = {li.get_attribute("data-place")
                  for li in browser.find_elements("css selector", "#tl-marking li")}
        board = data(browser, f"let j = -1; while (j + 1 < d.board.scans.length && "
                              f"d.board.scans[j + 1] <= {scan}) j += 1; return "
                              f"Object.keys(d.board.marking).filter(p => d.board.marking[p][j])")
        assert marked == set(board)
        # The window stays where it was scrubbed while the PLC scans on.
        frames = js(browser, "return softplc.frames")
        until(lambda: js(browser, "return softplc.frames") > frames + 5, 15, "frames go on")
        assert data(browser, f"return d.scans[{index}]") == scan

        # Why at a past scan: the trace CLI; at the newest scan, the PLC's own answer.
        browser.find_element("css selector", "#tl-transition option[value='hand_over']").click()
        browser.find_element("id", "tl-why").click()
        out = browser.find_element("id", "tl-why-out")
        assert f"softplc why hand_over --trace FILE --program PROGRAM.yaml --at-scan {scan}" \
            in out.text
        browser.find_element("id", "tl-live").click()
        until(lambda: js(browser, "return softplc.timeline.paused === false && "
                                  "softplc.timeline.data !== null && softplc.timeline.data"
                                  ".scans.length > 0"), 15, "live again")
        assert data(browser, "return d.scans[d.scans.length - 1]") > newest
        browser.find_element("id", "tl-why").click()
        until(lambda: out.text.startswith("hand_over: "), 15, "the PLC's why")
        assert "(the next round, after scan" in out.text
        assert errors(browser) == []
    finally:
        browser.get("about:blank")  # no page left reconnecting to a stopped softplc
        plc.close()
