"""The page's login (softplc/api/static/account.js, docs/web.md) in a real headless Chromium
against a real `softplc run` with two users made by `softplc users add`, as in
tests/security: a viewer logs in and sees who they are, their Stop is refused and the page
says so plainly with the way to log in; they log out; an operator logs in and Stop is
applied. The session cookie is the page's only credential (HttpOnly: no script reads it),
its requests pass the API's Origin check, and the trail names each step."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from softplc.api.client import ApiClient
from tests.support import free_port, softplc_run
from tests.web.test_browser import (  # noqa: F401 - `browser` is a pytest fixture
    ROOT,
    browser,
    errors,
    js,
    open_page,
    until,
)

PASSWORDS = {"op": "operator-pass-1", "view": "viewer-pass-1"}


def add_users(state: Path) -> None:
    for name, role in (("op", "operator"), ("view", "viewer")):
        added = subprocess.run([sys.executable, "-m", "softplc.cli", "users", "add", name,
                                "--role", role, "--state-dir", str(state)], cwd=ROOT,
                               input=PASSWORDS[name] + "\n", capture_output=True, text=True,
                               timeout=120)
        assert added.returncode == 0, added.stderr


@dataclass
class Plc:
    url: str
    client: ApiClient


@contextmanager
def running(state: Path) -> Iterator[Plc]:
    """`softplc run transport.yaml --start`, its API on a free loopback port, nothing else."""
    port = free_port()
    plc = Plc(f"http://127.0.0.1:{port}", ApiClient(f"http://127.0.0.1:{port}", timeout_s=10))
    with softplc_run(["programs/transport.yaml", "--start", "--api", f"127.0.0.1:{port}",
                      "--modbus", "off", "--opcua", "off", "--state-dir", str(state),
                      "--quiet", "--period", "10ms"],
                     lambda: plc.client.status()["state"] == "RUNNING",
                     stdout=subprocess.DEVNULL, what="softplc run answering and RUNNING"):
        yield plc


def shown(driver: Any, element: str) -> str:
    return str(driver.find_element("id", element).text)


def visible(driver: Any, element: str) -> bool:
    return bool(driver.find_element("id", element).is_displayed())


def log_in(driver: Any, name: str) -> None:
    driver.find_element("id", "login-open").click()
    until(lambda: js(driver, "return document.getElementById('token-dialog').open"), 10,
          "the login dialog opens")
    for field, value in (("login-user", name), ("login-password", PASSWORDS[name])):
        driver.find_element("id", field).clear()
        driver.find_element("id", field).send_keys(value)
    driver.find_element("id", "login-ok").click()
    # scrypt (~0.3 s, more on a loaded machine) before the answer
    until(lambda: not js(driver, "return document.getElementById('token-dialog').open"), 30,
          f"{name} is logged in", show=lambda: shown(driver, "login-error"))
    until(lambda: shown(driver, "who").startswith(name), 10, "the header names the user",
          show=lambda: shown(driver, "who"))


def test_a_viewer_is_refused_plainly_and_an_operator_stops_after_logging_in(
        browser: Any, tmp_path: Path) -> None:  # noqa: F811 - the fixture
    state = tmp_path / "state"
    add_users(state)
    with running(state) as plc:
        try:
            page(browser, plc)
        finally:
            browser.get("about:blank")  # no page left reconnecting to a stopped softplc
    trail = subprocess.run([sys.executable, "-m", "softplc.cli", "audit", "--json",
                            "--state-dir", str(state)], cwd=ROOT, capture_output=True,
                           text=True, timeout=120)
    steps = [(r["user"], r["via"], r["action"], r["outcome"])
             for r in map(json.loads, trail.stdout.splitlines()) if r["iface"] == "http"]
    assert steps == [("view", "failed", "login", "failed"),
                     ("view", "session", "login", "applied"),
                     ("view", "session", "POST stop", "denied"),
                     ("view", "session", "logout", "applied"),
                     ("op", "session", "login", "applied"),
                     ("op", "session", "POST stop", "applied")]


def page(driver: Any, plc: Plc) -> None:
    """The steps in the page: a viewer refused, logged out, an operator stopping."""
    open_page(driver, plc)
    until(lambda: shown(driver, "who") == "not logged in viewer (reads only)", 10,
          "the header says nobody is logged in", show=lambda: shown(driver, "who"))
    assert visible(driver, "login-open") and not visible(driver, "logout")

    # A wrong password: the dialog says so and stays open.
    driver.find_element("id", "login-open").click()
    driver.find_element("id", "login-user").send_keys("view")
    driver.find_element("id", "login-password").send_keys("not-the-password")
    driver.find_element("id", "login-ok").click()
    until(lambda: "wrong user name or password" in shown(driver, "login-error"), 30,
          "the failed login is shown", show=lambda: shown(driver, "login-error"))
    driver.find_element("id", "auth-cancel").click()

    log_in(driver, "view")
    assert shown(driver, "who") == "view viewer" and visible(driver, "logout")
    assert js(driver, "return document.cookie") == ""  # HttpOnly: no script reads it
    driver.find_element("css selector", 'button[data-command="stop"]').click()
    until(lambda: "stop refused: view is a viewer; stop needs an operator"
          in shown(driver, "message"), 15, "the refusal is said plainly",
          show=lambda: shown(driver, "message"))
    assert visible(driver, "offer-login")  # and the way to log in is offered
    assert plc.client.status()["state"] == "RUNNING"

    driver.find_element("id", "logout").click()
    until(lambda: shown(driver, "who") == "not logged in viewer (reads only)", 10,
          "logged out", show=lambda: shown(driver, "who"))
    assert shown(driver, "message") == "logged out" and visible(driver, "login-open")

    log_in(driver, "op")
    assert shown(driver, "who") == "op operator"
    driver.find_element("css selector", 'button[data-command="stop"]').click()
    until(lambda: shown(driver, "state") == "STOPPED", 15, "the stop is applied",
          show=lambda: shown(driver, "message"))
    assert plc.client.status()["state"] == "STOPPED"
    assert errors(driver, ("/api/v1/login - Failed to load resource: the server "
                            "responded with a status of 401",
                            "/api/v1/stop - Failed to load resource: the server "
                            "responded with a status of 403")) == []
