"""The setup view in a real browser (headless Debian Chromium, Playwright) against a real
``mazebot run --sim --room``: the polar plot fills in, a held jog button turns the wheels only with
the PIN, and releasing it stops them; a calibration started from the page shows its steps one by
one, and its Stop button stops the motors and writes nothing. Screenshots go to tests/web/artifacts/."""

from __future__ import annotations

import importlib.util
import json
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e '.[test]')")

# the daemon and browser settings of the page's own browser test (it skips without Chromium)
_spec = importlib.util.spec_from_file_location("_page_browser_test", Path(__file__).with_name("test_browser.py"))
_page_test = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_page_test)
ARTIFACTS, CHROMIUM, CHROMIUM_FLAGS = _page_test.ARTIFACTS, _page_test.CHROMIUM, _page_test.CHROMIUM_FLAGS
PHONE, PIN, Daemon = _page_test.PHONE, _page_test.PIN, _page_test.Daemon


def _setup(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "/api/setup", timeout=2) as resp:
        return json.load(resp)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    d = Daemon(tmp_path_factory.mktemp("setup-daemon"))
    with d.config.open("a") as config:  # the room: calibration needs 0.8 m straight runs, a maze cell has 0.3
        config.write('[sim]\nworld = "room"\n')
    d.start()
    yield d
    d.stop()
    assert "Traceback" not in d.log.read_text(), d.log.read_text()


@pytest.fixture(scope="module")
def page(daemon: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    with sync_api.sync_playwright() as pw:
        context, p = _page_test.open_phone_page(pw, tmp_path_factory.mktemp("setup-profile"), daemon.url + "/")
        yield p
        context.close()


def _hold(page: Any, selector: str, seconds: float) -> None:
    box = page.locator(selector).bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    time.sleep(seconds)
    page.mouse.up()


def test_the_setup_view_plots_the_raw_revolution(page, daemon) -> None:
    page.click("#setup-open")
    page.wait_for_selector("#setup:not([hidden])")
    page.wait_for_function("document.querySelectorAll('#polar circle.hit').length > 50", timeout=10_000)
    assert "samples valid" in page.inner_text("#setup-scan")
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    page.screenshot(path=str(ARTIFACTS / "phone-setup.png"))
    assert page.errors == []  # type: ignore[attr-defined]


def test_jogging_needs_the_pin_and_stops_on_release(page, daemon) -> None:
    before = _setup(daemon.url)["encoders"]
    page.fill("#setup-pin", "0000")
    _hold(page, "#jog-forward", 0.6)
    page.wait_for_function("document.getElementById('jog-status').textContent.includes('wrong PIN')")
    after_wrong = _setup(daemon.url)["encoders"]
    assert after_wrong["left_ticks"] == before["left_ticks"]  # a wrong PIN turns nothing
    page.fill("#setup-pin", PIN)
    _hold(page, "#jog-forward", 1.0)
    time.sleep(0.5)  # well past the time-to-live: the wheels are at rest again
    driven = _setup(daemon.url)
    assert driven["encoders"]["left_ticks"] > before["left_ticks"] + 20
    assert driven["encoders"]["right_ticks"] > before["right_ticks"] + 20
    assert driven["throttles"] == [0.0, 0.0]
    time.sleep(0.5)
    rest = _setup(daemon.url)["encoders"]
    for side in ("left_ticks", "right_ticks"):  # released: nothing turns any more (the page sends one jog
        assert rest[side] == driven["encoders"][side]  # at a time, so no drive request overtakes the release)
    assert page.evaluate("localStorage.getItem('mazebot.pin')") == PIN
    assert page.errors == []  # type: ignore[attr-defined]


def test_the_doctor_results_are_listed(page, daemon) -> None:
    page.click("#doctor-run")
    page.wait_for_selector("#doctor li[data-status]")
    text = page.inner_text("#doctor")
    assert "free space" in text and "lidar revolution" in text and "clock" in text
    page.screenshot(path=str(ARTIFACTS / "phone-setup-doctor.png"), full_page=True)
    assert page.errors == []  # type: ignore[attr-defined]


def test_a_calibration_shows_its_steps_and_stops_from_the_page(page, daemon) -> None:
    config_before = daemon.config.read_text()
    page.fill("#setup-pin", PIN)
    page.click("#calib-start")
    page.wait_for_selector("#calib[data-status='running']")
    assert [page.get_attribute(f"#calib-steps li:nth-child({i})", "data-step") for i in range(1, 6)] == [
        "wiring", "ramp", "straight", "turns", "yaw"]
    # the first step finds the wiring with a pulse of each motor, then the throttle ramp begins
    page.wait_for_selector("#calib-steps li[data-step='wiring'][data-state='done']", timeout=90_000)
    assert "left wheel: motor output" in page.inner_text("#calib-steps li[data-step='wiring']")
    page.wait_for_selector("#calib-steps li[data-step='ramp'][data-state='running']", timeout=30_000)
    assert "step 2 of 5" in page.inner_text("#calib-status")
    page.screenshot(path=str(ARTIFACTS / "phone-setup-calibration.png"), full_page=True)
    page.click("#calib-stop")
    page.wait_for_selector("#calib[data-status='stopped']", timeout=10_000)
    assert "stopped from the page" in page.inner_text("#calib-steps li[data-step='ramp']")
    assert "nothing was written" in page.inner_text("#calib-status")
    assert page.is_visible("#calib-start") and not page.is_visible("#calib-write")
    time.sleep(0.3)  # a control tick or two
    assert _setup(daemon.url)["throttles"] == [0.0, 0.0]
    assert daemon.config.read_text() == config_before
    assert not daemon.config.with_name("config.toml.bak").exists()
    assert page.errors == []  # type: ignore[attr-defined]

