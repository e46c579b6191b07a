"""The page in a real browser: headless Debian Chromium on a phone-sized screen, driven by Playwright,
against a real ``mazebot run --sim``. Screenshots go to tests/web/artifacts/."""

from __future__ import annotations

import io
import json
import os
import re
import shutil
import signal
import struct
import subprocess
import sys
import time
import urllib.request
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp.test_utils import unused_port

pytestmark = pytest.mark.slow  # a real Chromium on the running daemon

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
def playwright() -> Iterator[Any]:
    with sync_api.sync_playwright() as pw:
        yield pw


def open_phone_page(pw: Any, profile: Path, url: str) -> tuple[Any, Any]:
    """Chromium as a phone (``PHONE``, touch) with a fresh profile, on ``url``: (context, page).

    ``page.errors`` collects the page's uncaught script errors; the caller closes the context.
    """
    ARTIFACTS.mkdir(exist_ok=True)
    context = pw.chromium.launch_persistent_context(
        str(profile),  # a fresh --user-data-dir
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
    page.errors = []
    page.on("pageerror", lambda exc: page.errors.append(str(exc)))
    page.goto(url)
    return context, page


@pytest.fixture(scope="module")
def browser_page(daemon: Daemon, playwright: Any, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    context, page = open_phone_page(playwright, tmp_path_factory.mktemp("profile"), daemon.url + "/")
    yield page
    context.close()


def _wait_state(page: Any, daemon: Daemon, state: str, timeout_s: float = 15.0) -> float:
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
    _wait_state(page, daemon, "exploring")  # how fast is bench/stop_latency.py's figure, not a test's
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


def test_the_chart_draws_coverage_and_distance_as_the_run_proceeds(browser_page, daemon) -> None:
    page = browser_page
    page.click("#go")  # the PIN is remembered
    _wait_state(page, daemon, "exploring")
    page.wait_for_function("mazebot.progress.points().length >= 5", timeout=10_000)
    first = page.evaluate("mazebot.progress.points()")
    page.wait_for_function(f"mazebot.progress.points().at(-1)[0] > {first[-1][0]} + 3", timeout=15_000)
    page.wait_for_function("mazebot.progress.points().at(-1)[2] > 0.1", timeout=15_000)
    points = page.evaluate("mazebot.progress.points()")
    times = [p[0] for p in points]
    assert times == sorted(times) and len(points) > len(first)
    assert all(p[2] is not None and p[2] >= 0 for p in points)
    distances = [p[2] for p in points]
    assert distances == sorted(distances)  # driven distance never goes down within a run
    status = _status(daemon.url)
    assert status["distance_m"] >= distances[-1] - 0.05  # the robot's own count, a little later
    # the lines are drawn: one point per sample in the path of each series
    d = page.get_attribute("#chart path.line.dist", "d")
    assert d and d.startswith("M") and d.count("L") >= len(points) - 2
    if any(p[1] is not None for p in points):
        assert page.get_attribute("#chart path.line.cov", "d")
    label = page.get_attribute("#chart", "aria-label")
    assert "driven after" in label and page.get_attribute("#map", "role") == "img"
    assert page.get_attribute("#state", "aria-live") == "polite"
    page.screenshot(path=str(ARTIFACTS / "phone-progress.png"))
    page.click("#go")
    _wait_state(page, daemon, "stopped")
    assert page.errors == []  # type: ignore[attr-defined]


def _pgm(data: bytes) -> tuple[int, int, bytes]:
    magic, comment, size, maxval, pixels = data.split(b"\n", 4)
    assert magic == b"P5" and comment.startswith(b"#") and maxval == b"255"
    cols, rows = map(int, size.split())
    return cols, rows, pixels


def test_the_map_downloads_as_png_and_as_a_ros_map_of_one_snapshot(browser_page, tmp_path) -> None:
    page = browser_page
    page.click("#save summary")
    with page.expect_download() as info:
        page.click("#save-png")
    png = info.value
    assert re.fullmatch(r"mazebot-map-\d{8}-\d{6}\.png", png.suggested_filename), png.suggested_filename
    data = Path(png.path()).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = struct.unpack(">II", data[16:24])
    (idat_len,) = struct.unpack(">I", data[33:37])
    assert len(zlib.decompress(data[41 : 41 + idat_len])) == height * (width + 1)  # greyscale rows decode
    with page.expect_download() as info:
        page.click("#save-ros")
    ros = info.value
    stem = ros.suggested_filename.removesuffix(".zip")
    assert re.fullmatch(r"mazebot-map-\d{8}-\d{6}", stem), ros.suggested_filename
    with zipfile.ZipFile(io.BytesIO(Path(ros.path()).read_bytes())) as zf:
        assert sorted(zf.namelist()) == [f"{stem}.pgm", f"{stem}.yaml"]
        cols, rows, pixels = _pgm(zf.read(f"{stem}.pgm"))
        yaml = zf.read(f"{stem}.yaml").decode()
    assert len(pixels) == cols * rows and set(pixels) <= {0, 205, 254}
    assert f"image: {stem}.pgm\n" in yaml and "mode: trinary" in yaml
    resolution = float(re.search(r"^resolution: (.+)$", yaml, re.M).group(1))
    origin = [float(v) for v in re.search(r"^origin: \[(.+)\]$", yaml, re.M).group(1).split(",")]
    assert resolution > 0 and origin[2] == 0.0
    # the live map is bigger than the empty start and the page's copy of it has the same geometry
    assert cols * rows > 100
    assert page.evaluate("mazebot.view.grid.res") == pytest.approx(resolution)
    assert "saved" in page.inner_text("#save-msg")
    page.click("#save summary")
    assert page.errors == []  # type: ignore[attr-defined]


def test_the_chart_history_stays_bounded_over_a_long_run(browser_page) -> None:
    """An hour of 5 Hz status (18 000 packets) keeps at most 300 samples, spanning the whole hour."""
    page = browser_page
    kept = page.evaluate("""() => {
        const sizes = [];
        for (let i = 0; i <= 18000; i++) {
            const t = 5000 + i / 5;  // later than the real run, so it reads as the same run going on
            document.dispatchEvent(new CustomEvent("mazebot:status",
                { detail: { elapsed_s: t, coverage: i / 18000, distance_m: i / 50 } }));
            sizes.push(mazebot.progress.series.points.length);
        }
        const pts = mazebot.progress.points();
        return { max: Math.max(...sizes), first: pts[0][0], last: pts.at(-1), n: pts.length };
    }""")
    assert kept["max"] <= 300 and kept["n"] >= 100
    assert kept["last"] == [5000 + 3600, 1, 360]  # the newest sample is always the current state
    assert kept["first"] < 5000 + 60  # ... and the oldest still the start of the hour
    assert page.errors == []  # type: ignore[attr-defined]


def test_a_browser_without_decompression_stream_says_so_and_never_loops_on_resyncs(
        daemon, playwright, tmp_path) -> None:
    browser = playwright.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS,
                                         env={**os.environ, "NO_PROXY": "127.0.0.1,localhost"})
    try:
        context = browser.new_context(viewport=PHONE, is_mobile=True, has_touch=True)
        context.add_init_script("delete window.DecompressionStream")
        page = context.new_page()
        sockets: list[str] = []
        page.on("websocket", lambda ws: sockets.append(ws.url))
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(daemon.url + "/")
        page.wait_for_selector("#unsupported", state="visible", timeout=5000)
        assert "DecompressionStream" in page.inner_text("#unsupported")
        assert "Safari 16.4" in page.inner_text("#unsupported")
        # the state still shows, from /api/status, and the button works over HTTP
        page.wait_for_function("document.body.dataset.state !== 'unknown'", timeout=5000)
        assert page.inner_text("#conn-text") == "status only"
        time.sleep(3)
        assert sockets == [] and errors == []
        assert page.evaluate("mazebot.stats.resyncs") == 0 and page.evaluate("mazebot.stats.packets") == 0
        page.screenshot(path=str(ARTIFACTS / "phone-no-decompressionstream.png"))
    finally:
        browser.close()


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
