"""The page in a real browser: headless Debian Chromium on a phone-sized screen, driven by Playwright,
against a real ``mazebot run --sim``. Screenshots go to tests/web/artifacts/."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp.test_utils import unused_port

sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed (pip install -e '.[test]')")

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not Path(CHROMIUM).exists():
    pytest.skip("Debian's chromium is not installed (.ci/run installs it: apt-get install chromium chromium-driver)",
                allow_module_level=True)

ARTIFACTS = Path(__file__).parent / "artifacts"
PIN = "2468"
PHONE = {"width": 360, "height": 640}
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]


def _status(url: str) -> dict[str, Any]:
    with urllib.request.urlopen(url + "/api/status", timeout=2) as resp:
        return json.load(resp)


class Daemon:
    """``mazebot run --sim`` in a subprocess, on its own port and state dir."""

    def __init__(self, tmp: Path) -> None:
        self.port = unused_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.config = tmp / "config.toml"
        self.config.write_text(
            f'[web]\ncontrol_token = "{PIN}"\nheartbeat_s = 1.0\n[daemon]\nstate_dir = "{tmp / "state"}"\n'
        )
        self.log = tmp / "daemon.log"
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "mazebot", "run", "--sim", "--config", str(self.config),
                 "--host", "127.0.0.1", "--port", str(self.port)],
                stdout=log, stderr=log,
            )
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            try:
                _status(self.url)
                return
            except OSError:
                assert self.proc.poll() is None, self.log.read_text()
                time.sleep(0.1)
        raise AssertionError("mazebot run --sim did not serve within 15 s:\n" + self.log.read_text())

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                assert self.proc.wait(timeout=10) == 0, self.log.read_text()
            finally:
                if self.proc.poll() is None:
                    self.proc.kill()


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    d = Daemon(tmp_path_factory.mktemp("daemon"))
    d.start()
    yield d
    d.stop()
    assert "Traceback" not in d.log.read_text(), d.log.read_text()


@pytest.fixture(scope="module")
def browser_page(daemon: Daemon, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    ARTIFACTS.mkdir(exist_ok=True)
    with sync_api.sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path_factory.mktemp("profile")),  # a fresh --user-data-dir
            executable_path=CHROMIUM,
            headless=True,
            args=CHROMIUM_FLAGS,
            viewport=PHONE,
            device_scale_factor=2,
            is_mobile=True,
            has_touch=True,
            env={**os.environ, "NO_PROXY": "127.0.0.1,localhost"},
        )
        page = context.pages[0] if context.pages else context.new_page()
        page.errors = []  # type: ignore[attr-defined]
        page.on("pageerror", lambda exc: page.errors.append(str(exc)))  # type: ignore[attr-defined]
        page.goto(daemon.url + "/")
        yield page
        context.close()


def _wait_state(page: Any, daemon: Daemon, state: str, timeout_s: float = 3.0) -> float:
    """Seconds until both the page and the daemon show ``state``."""
    t0 = time.monotonic()
    page.wait_for_function(f"document.body.dataset.state === {state!r}", timeout=timeout_s * 1000)
    assert _status(daemon.url)["state"] == state
    return time.monotonic() - t0


def test_the_page_loads_and_goes_live_on_a_phone_screen(browser_page, daemon) -> None:
    page = browser_page
    page.wait_for_selector("body[data-conn='open']", timeout=10_000)
    assert page.inner_text("#conn-text") == "live"
    _wait_state(page, daemon, "idle")
    assert page.inner_text("#go") == "Start" and page.is_enabled("#go")
    # the phone screen: nothing wider than the viewport, the button within thumb reach
    assert page.evaluate("document.documentElement.scrollWidth") <= PHONE["width"]
    box = page.locator("#go").bounding_box()
    assert box["y"] + box["height"] <= PHONE["height"] and box["height"] >= 56
    assert page.locator("#map").bounding_box()["height"] > 300
    page.screenshot(path=str(ARTIFACTS / "phone-idle.png"))
    assert page.errors == []  # type: ignore[attr-defined]


def test_pin_is_asked_once_remembered_and_start_stop_change_the_state(browser_page, daemon) -> None:
    page = browser_page
    page.click("#go")
    page.wait_for_selector("#pin-dialog[open]")
    page.fill("#pin", "0000")
    page.click("#pin-ok")
    page.wait_for_function("document.getElementById('pin-hint').textContent.includes('Wrong PIN')")
    page.wait_for_selector("#pin-dialog[open]")
    assert _status(daemon.url)["state"] == "idle"  # a wrong PIN moves nothing
    page.fill("#pin", PIN)
    page.click("#pin-ok")
    took_s = _wait_state(page, daemon, "exploring")
    assert took_s < 1.0
    assert page.inner_text("#go") == "Stop"
    assert page.evaluate("localStorage.getItem('mazebot.pin')") == PIN
    page.screenshot(path=str(ARTIFACTS / "phone-running.png"))
    page.click("#go")  # the PIN is remembered: no dialog this time
    _wait_state(page, daemon, "stopped")
    assert not page.is_visible("#pin-dialog")
    assert page.inner_text("#go") == "Start"
    assert page.errors == []  # type: ignore[attr-defined]


def test_a_sequence_gap_makes_the_page_ask_for_a_full_map(browser_page) -> None:
    page = browser_page
    fulls = page.evaluate("mazebot.stats.fulls")
    page.evaluate("mazebot.view.seq -= 1")  # as if a packet was lost; the next heartbeat reveals it
    page.wait_for_function(f"mazebot.stats.resyncs >= 1 && mazebot.stats.fulls > {fulls}", timeout=5000)
    assert page.evaluate("mazebot.view.awaitingFull") is False


def test_the_map_canvas_fills_in(browser_page, daemon) -> None:
    page = browser_page
    deadline = time.monotonic() + 20
    while _status(daemon.url)["map"] is None and time.monotonic() < deadline:
        time.sleep(0.5)
    assert _status(daemon.url)["map"] is not None, "SLAM published no map within 20 s"
    page.wait_for_function("mazebot.knownCells().free > 200 && mazebot.knownCells().occupied > 20", timeout=20_000)
    assert page.evaluate("mazebot.drawnPixels()") > 10_000
    assert page.is_hidden("#empty")
    page.screenshot(path=str(ARTIFACTS / "phone-map.png"))


def test_the_page_reconnects_after_the_daemon_restarts(browser_page, daemon) -> None:
    page = browser_page
    fulls = page.evaluate("mazebot.stats.fulls")
    daemon.stop()
    page.wait_for_selector("body[data-conn='closed']", timeout=5000)
    assert "offline" in page.inner_text("#conn-text")
    daemon.start()
    page.wait_for_selector("body[data-conn='open']", timeout=15_000)
    page.wait_for_function(f"mazebot.stats.fulls > {fulls}", timeout=5000)
    _wait_state(page, daemon, "idle")
    page.screenshot(path=str(ARTIFACTS / "phone-reconnected.png"))
