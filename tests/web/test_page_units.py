"""Issue 39, item 1 on the operator's page, in a real headless Chromium against a real
`softplc run programs/tank.yaml`: a scaled symbol shows its engineering value at its scale's
resolution with its unit (`47.002 %`, never the raw count or a double's noise), its input
boxes offer the engineering range (0..100 %, not the int's -32768..32767), a value typed in
engineering units is what the program reads, and the process image table fits its card in a
1400 px wide window. The page learns unit, range and precision from GET /api/v1/net
(softplc/core/present.py's entry_form), so it has no second copy of the rule."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from tests.web.test_browser import (  # noqa: F401 (browser: a fixture)
    Softplc,
    browser,
    give_key,
    js,
    open_page,
    pytestmark,
    until,
)


def row_of(driver: Any, name: str) -> Any:
    return driver.find_element("css selector", f'#image tr[data-symbol="{name}"]')


def test_tank_page_shows_units_and_takes_engineering_ranges(browser: Any, tmp_path: Path  # noqa: F811
                                                            ) -> None:
    plc = Softplc("programs/tank.yaml", tmp_path / "state")
    try:
        browser.set_window_size(1400, 1000)
        open_page(browser, plc)
        level = row_of(browser, "level")
        boxes = {b.get_attribute("class"): b for b in level.find_elements("css selector", "input")}
        assert list(boxes) == ["force"]  # an input: forced, not written
        force = boxes["force"]
        assert force.get_attribute("placeholder") == "0..100 %"
        assert (force.get_attribute("data-min"), force.get_attribute("data-max")) == ("0", "100")
        temperature = row_of(browser, "temperature").find_element("css selector", "input.force")
        assert temperature.get_attribute("placeholder") == "-50..150 °C"
        fill_to = row_of(browser, "fill_to").find_element("css selector", "input.write")
        assert fill_to.get_attribute("placeholder") == "a number, e.g. 12.5"
        batches = row_of(browser, "batches").find_element("css selector", "input.write")
        assert batches.get_attribute("placeholder") == "-2147483648..2147483647"
        shown = lambda name: row_of(browser, name).find_element(  # noqa: E731
            "css selector", "td.value").text
        until(lambda: re.fullmatch(r"-?\d+\.\d °C", shown("temperature")), 10,
              "the temperature shows to 0.1 °C with its unit", show=lambda: shown("temperature"))
        assert shown("temperature").endswith("°C")
        until(lambda: re.fullmatch(r"\d+\.\d{3} %", shown("level")), 10,
              "the level shows to 0.001 % with its unit", show=lambda: shown("level"))
        assert shown("fill_to") == "80"  # a real shown as the program reads it, no bits

        # A force typed in engineering units is what the program reads (47.0 % is raw 12995).
        force.send_keys("47")
        level.find_element("css selector", "button.force").click()
        give_key(browser, (tmp_path / "state" / "api_token").read_text().strip())
        force.clear()
        force.send_keys("47")
        level.find_element("css selector", "button.force").click()
        until(lambda: "forced" in level.get_attribute("class"), 15, "level is forced",
              show=lambda: browser.find_element("id", "message").text)
        until(lambda: shown("level") == "47.002 %", 10, "the forced level shows",
              show=lambda: shown("level"))
        assert round(float(plc.client.read_symbol("level")), 4) == 47.0016  # raw 12995
        assert browser.find_element("id", "message").text == \
            "force: level = 47.002 (state RUNNING)"  # not 47.00159143518518

        # Why nothing moves (issue 39 item 6): with the level held at 47 %, the tank waits
        # for it to reach the setpoint, or (idle) for a warmer temperature; the net card says
        # which and what blocks it, in net time, the values as the program reads them.
        waits = lambda: [li.text for li in browser.find_elements(  # noqa: E731
            "css selector", "#waiting li")]
        said = re.compile(r"(start_fill|reached) waits \d+\.\d s \(net time\): guard .+ is "
                          r"false with .*(level = 47\.002 %|temperature = -?\d+\.\d °C).*")
        until(lambda: any(said.fullmatch(w) for w in waits()), 15,
              "the net card says what the tank waits for", show=waits)

        # The recent past's image shows them the same way (it showed 21.200000000000003).
        past = lambda name: browser.find_element(  # noqa: E731
            "css selector", f'#tl-image tr[data-name="{name}"]').find_elements(
            "tag name", "td")[1].text
        until(lambda: past("level") == "47.002 %", 15, "the recent past shows the level",
              show=lambda: past("level"))
        # Read while the table stands (a refresh between finding a row and reading it made
        # the element stale beside 4 busy loops); then the value's form, exactly.
        temperature = until(lambda: past("temperature"), 15, "the recent past's temperature")
        assert re.fullmatch(r"-?\d+\.\d °C", temperature), temperature
        browser.find_element("id", "tl-name").send_keys("temperature")
        browser.find_element("id", "tl-plot").click()
        legend = until(lambda: js(browser, "const p = softplc.timeline.plot;"
                                           "const s = p && p.series[1];"
                                           "return s && s._raw && s.value(p, null, 1, "
                                           "s._raw.length - 1)"), 10, "the plot's legend")
        assert re.fullmatch(r"-?\d+\.\d °C", legend), legend  # the plot's legend too

        # The process image table fits its card at 1400 px: no horizontal scroll bar.
        fit = js(browser, "const card = document.querySelector('.image-card');"
                          "const table = document.getElementById('image');"
                          "return [card.scrollWidth, card.clientWidth, "
                          "table.getBoundingClientRect().width, window.innerWidth];")
        js(browser, "document.getElementById('image').scrollIntoView()")
        browser.save_screenshot(str(tmp_path / "tank-1400.png"))
        assert js(browser, "const q = (s) => document.querySelector("
                           "'#image tr[data-symbol=level] ' + s).getBoundingClientRect();"
                           "return q('button.release').top < q('input.force').bottom"), \
            "the force box and its buttons on one line"
        assert fit[0] <= fit[1], f"image table {fit[2]:.0f} px in a card {fit[1]} px wide " \
                                 f"(window {fit[3]} px)"
    finally:
        browser.get("about:blank")
        browser.set_window_size(1500, 1100)
        plc.close()
