"""``mazebot replay --serve``: a recording played back behind the real web application.

A short simulated run (the minimaze, scripted drive, virtual time) is recorded once per
module; its offline replay is the ground truth. A websocket client (aiohttp) that applies
the packets as the page does must end with exactly the offline replay's map, having seen
the map grow through deltas; the page in headless Chromium says it is a replay.
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from aiohttp.test_utils import unused_port

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config
from mazebot.record import replay_server
from mazebot.record.reader import Recording
from mazebot.record.replay import ReplayResult, replay
from mazebot.state import SharedState
from mazebot.web.app import WebSettings
from mazebot.web.protocol import KIND_FULL, CellsSection, GridSection, decode_packet, three_state_to_codes

pytestmark = pytest.mark.slow  # a whole simulated run recorded first, then served

MAZE = str(Path(__file__).resolve().parents[2] / "mazebot" / "sim" / "mazes" / "minimaze.txt")


@dataclass
class Recorded:
    path: Path
    offline: ReplayResult
    duration_s: float


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Recorded:
    path = tmp_path_factory.mktemp("served") / "short.mcap"
    run_one(Config(), RunSpec(maze_path=MAZE, size=None, seed=1, max_sim_s=30.0, record_path=str(path)))
    recording = Recording.open(path)
    times = [m.log_time_ns for m in recording.messages(["/mazebot/encoders"])]
    offline = replay(recording)
    assert offline.updates > 50 and offline.slam.grid is not None
    return Recorded(path, offline, (times[-1] - times[0]) / 1e9)


class PageMirror:
    """What the page does with packets (docs/protocol.md, "Applying packets"); a gap is a failure here."""

    def __init__(self) -> None:
        self.seq: int | None = None
        self.epoch: int | None = None
        self.codes: np.ndarray | None = None
        self.geometry: tuple[float, tuple[float, float]] | None = None
        self.status: dict[str, Any] = {}
        self.trail: list[float] = []
        self.fulls = 0
        self.deltas_with_cells = 0
        self.cells_patched = 0
        self.first_known: int | None = None  # known cells of the first map seen

    def apply(self, data: bytes) -> None:
        p = decode_packet(data)
        if p.kind == KIND_FULL:
            self.fulls += 1
            self.status = dict(p.status)
            self.trail = list(p.status.get("trail", []))
            if isinstance(p.map, GridSection):
                self.epoch, self.codes = p.map.epoch, p.map.codes.copy()
                self.geometry = (p.map.resolution_m, p.map.origin_m)
                if self.first_known is None:
                    self.first_known = int(np.count_nonzero(self.codes))
        else:
            assert self.seq is not None and p.seq == self.seq + 1, (self.seq, p.seq)
            self.status.update(p.status)
            self.trail = list(p.status["trail"]) if "trail" in p.status else self.trail + p.status.get("trail+", [])
            if isinstance(p.map, CellsSection):
                assert p.map.epoch == self.epoch and self.codes is not None
                self.codes.reshape(-1)[p.map.indices] = p.map.codes
                self.deltas_with_cells += 1
                self.cells_patched += len(p.map)
        self.seq = p.seq


async def test_a_websocket_client_watches_the_replay_and_ends_with_the_offline_map(recorded: Recorded) -> None:
    state = SharedState()
    speed = max(1.0, recorded.duration_s / 4.0)  # about four seconds of replay: many broadcasts
    recording = Recording.open(recorded.path)
    progress = replay_server.ReplayProgress.of(recording, speed)
    settings = WebSettings(control_token="1234", broadcast_hz=10.0, heartbeat_s=0.3)
    port = unused_port()
    runner = await replay_server.start_server(state, progress, settings, "127.0.0.1", port)
    executor = ThreadPoolExecutor(max_workers=1)
    mirror = PageMirror()
    replies: list[dict[str, Any]] = []
    poses: set[tuple[float, ...]] = set()
    try:
        async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
            hello = json.loads((await ws.receive(timeout=5)).data)
            assert hello["type"] == "hello" and hello["replay"]["file"] == "short.mcap"
            assert hello["replay"]["speed"] == speed and hello["replay"]["finished"] is False
            feeding = asyncio.create_task(replay_server.feed(recording, state, progress, executor))
            await ws.send_str(json.dumps({"type": "start", "token": "1234"}))  # the right PIN: still no robot
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                msg = await ws.receive(timeout=5)
                if msg.type == aiohttp.WSMsgType.BINARY:
                    mirror.apply(msg.data)
                    poses.add(tuple(mirror.status.get("pose") or ()))
                    continue
                text = json.loads(msg.data)
                if text["type"] == "reply":
                    replies.append(text)
                elif text["type"] == "heartbeat" and feeding.done() and text["seq"] == mirror.seq:
                    break  # the replay is over and the last packet was applied: nothing more is coming
            else:
                raise AssertionError("the served replay did not finish within 60 s")
            served = feeding.result()
            async with http.post(f"http://127.0.0.1:{port}/api/stop", headers={"X-Mazebot-Token": "1234"}) as resp:
                assert resp.status == 409 and "replay of short.mcap" in (await resp.json())["error"]
            async with http.get(f"http://127.0.0.1:{port}/api/status") as resp:
                status = await resp.json()
    finally:
        await runner.cleanup()
        executor.shutdown()
    assert replies == [{"type": "reply", "command": "start", "ok": False, "status": 409,
                        "message": "this page shows a replay of short.mcap: there is no robot to start"}]
    assert status["replay"] == {"file": "short.mcap", "speed": speed, "progress": 1.0, "finished": True}
    # the same SLAM, the same steps: the served map is the offline map, cell for cell
    assert served.updates == recorded.offline.updates and served.applied == recorded.offline.applied
    grid = recorded.offline.slam.grid
    assert mirror.geometry == (grid.resolution_m, tuple(grid.origin_m))
    np.testing.assert_array_equal(mirror.codes, three_state_to_codes(grid.three_state()))
    # ... and it was watched growing: deltas patched the map, the robot and its trail moved
    assert mirror.deltas_with_cells >= 2 and mirror.cells_patched > 100, (mirror.fulls, mirror.deltas_with_cells)
    assert mirror.first_known is not None and mirror.first_known < 0.9 * np.count_nonzero(mirror.codes)
    assert len(poses) >= 5
    keyframes = recorded.offline.slam.keyframe_poses()
    trail = np.reshape(mirror.trail, (-1, 2))  # 1 cm rounding; a keyframe on the spot of the last is not resent
    gaps_m = np.min(np.hypot(*(keyframes[:, None, :2] - trail[None, :, :]).transpose(2, 0, 1)), axis=1)
    # keyframes taken while turning on the spot share a trail point: count the distinct spots
    moved_m = np.hypot(*np.diff(keyframes[:, :2], axis=0).T)
    spots = 1 + int(np.count_nonzero(moved_m >= 0.01))
    assert gaps_m.max() < 0.012 and len(trail) >= 0.8 * spots, (len(trail), spots, len(keyframes))
    np.testing.assert_allclose(trail[-1], keyframes[-1, :2], atol=0.006)
    assert status["state"] == mirror.status["state"] != "idle"  # the recorded run state, not a robot's


class ServedReplay:
    """``mazebot replay FILE --serve`` in a subprocess, on its own port."""

    def __init__(self, recording: Path, tmp: Path, speed: float) -> None:
        self.port = unused_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.out = tmp / "out"
        config = tmp / "config.toml"
        config.write_text('[web]\nheartbeat_s = 1.0\n')
        self.log = tmp / "replay.log"
        with open(self.log, "wb") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "mazebot", "replay", str(recording), "--serve", "--speed", str(speed),
                 "--host", "127.0.0.1", "--port", str(self.port), "--out", str(self.out), "--config", str(config)],
                stdout=subprocess.PIPE, stderr=log, text=True,
            )

    def status(self) -> dict[str, Any]:
        with urllib.request.urlopen(self.url + "/api/status", timeout=2) as resp:
            return json.load(resp)

    def wait_serving(self) -> None:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                self.status()
                return
            except OSError:
                assert self.proc.poll() is None, self.log.read_text()
                time.sleep(0.1)
        raise AssertionError("mazebot replay --serve did not serve within 20 s:\n" + self.log.read_text())

    def stop(self) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            out, _ = self.proc.communicate(timeout=15)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
        return self.proc.returncode, out


@pytest.fixture(scope="module")
def served(recorded: Recorded, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServedReplay]:
    server = ServedReplay(recorded.path, tmp_path_factory.mktemp("cli"), speed=max(1.0, recorded.duration_s / 8.0))
    try:
        server.wait_serving()
        yield server
    finally:
        server.stop()


CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"


def test_the_phone_page_says_it_is_a_replay(served: ServedReplay, tmp_path: Path) -> None:
    """(Runs before the CLI test below, which stops the served replay.)"""
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian's chromium is not installed (.ci/run installs it)")
    with sync_api.sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True,
            args=["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking"],
            viewport={"width": 360, "height": 640}, is_mobile=True, has_touch=True,
            env={**os.environ, "NO_PROXY": "127.0.0.1,localhost"},
        )
        try:
            page = context.pages[0] if context.pages else context.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda exc: errors.append(str(exc)))
            page.goto(served.url + "/")
            page.wait_for_selector("body[data-replay='1'][data-conn='open']", timeout=10_000)
            assert page.inner_text("#conn-text") == "replay"
            assert page.inner_text("#replay").startswith("Replay of short.mcap at ")
            assert page.inner_text("#go") == "Replay" and not page.is_enabled("#go")
            page.wait_for_function("mazebot.knownCells().free > 200 && mazebot.knownCells().occupied > 20",
                                   timeout=30_000)
            assert errors == []
        finally:
            context.close()


def test_the_cli_serves_the_replay_refuses_control_and_writes_the_outputs(served: ServedReplay,
                                                                          recorded: Recorded) -> None:
    request = urllib.request.Request(served.url + "/api/start", method="POST", headers={"X-Mazebot-Token": "0"})
    with pytest.raises(urllib.error.HTTPError) as refused:
        urllib.request.urlopen(request, timeout=2)
    assert refused.value.code == 409
    refused.value.close()  # the error holds the response's socket
    deadline = time.monotonic() + 60
    while not served.status()["replay"]["finished"]:
        assert time.monotonic() < deadline, "the replay did not finish within 60 s"
        time.sleep(0.2)
    assert served.status()["replay"]["progress"] == 1.0
    with urllib.request.urlopen(served.url + "/map.pgm", timeout=2) as resp:
        assert resp.read().startswith(b"P5")
    code, stdout = served.stop()
    assert code == 0, served.log.read_text()
    summary = json.loads(stdout.strip().splitlines()[-1])
    assert summary["updates"] == recorded.offline.updates and summary["out"] == str(served.out)
    assert (served.out / "map.yaml").is_file()
    assert "Traceback" not in served.log.read_text()


def test_serving_on_a_port_in_use_is_one_line_exit_69(recorded: Recorded, tmp_path: Path) -> None:
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = subprocess.run(
            [sys.executable, "-m", "mazebot", "replay", str(recorded.path), "--serve", "--host", "127.0.0.1",
             "--port", str(port), "--out", str(tmp_path / "out")],
            capture_output=True, text=True, timeout=60,
        )
    assert done.returncode == 69, done.stderr
    assert done.stderr.strip().count("\n") == 0 and f"127.0.0.1:{port}" in done.stderr
    assert not (tmp_path / "out").exists()  # nothing half-written


def test_host_and_port_without_serve_is_a_usage_error(recorded: Recorded) -> None:
    done = subprocess.run([sys.executable, "-m", "mazebot", "replay", str(recorded.path), "--port", "8080"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--serve" in done.stderr and done.stderr.count("\n") == 1
