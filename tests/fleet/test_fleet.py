"""The fleet over Zenoh: two simulated robots in two processes, a watcher that finds both.

Real parts: ``mazebot run --sim`` subprocesses with ``[zenoh]`` on, real Zenoh sessions on
loopback (explicit TCP endpoints, multicast scouting off so other Zenoh programs on this
machine are not found), the robots' own web pages, and the watcher's aiohttp application.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import numpy as np
import pytest
from aiohttp.test_utils import TestClient, TestServer, unused_port

from mazebot.config import Config, ZenohConfig
from mazebot.errors import ConfigError, HardwareUnavailable
from mazebot.fleet import keys
from mazebot.fleet.watcher import RobotMirror
from mazebot.web.protocol import KIND_DELTA, KIND_FULL, CellsSection, GridSection, Packet, encode_packet

pytestmark = pytest.mark.slow  # daemons and watchers over real Zenoh sessions

PIN = "2468"
NAMES = ("alpha", "beta")


# -- pure parts -------------------------------------------------------------------------------


def _full(seq: int, codes: np.ndarray, epoch: int = 1) -> bytes:
    return encode_packet(Packet(KIND_FULL, seq, {"state": "idle", "trail": [0.0, 0.0]},
                                GridSection(epoch, 0.02, (-1.0, -1.0), codes)))


def _delta(seq: int, indices: list[int], values: list[int], epoch: int = 1, **status: object) -> bytes:
    cells = CellsSection(epoch, np.array(indices, dtype=np.int64), np.array(values, dtype=np.uint8))
    return encode_packet(Packet(KIND_DELTA, seq, dict(status), cells))


def test_mirror_applies_deltas_like_the_page_and_waits_for_a_full_after_a_gap() -> None:
    codes = np.zeros((4, 5), dtype=np.uint8)
    mirror = RobotMirror("alpha")
    assert mirror.apply(_delta(1, [0], [1])) == "ignored"  # nothing to patch before a full map
    assert mirror.apply(_full(7, codes)) == "applied"
    assert mirror.apply(_delta(8, [3, 19], [2, 1], state="exploring", **{"trail+": [0.1, 0.2]})) == "applied"
    expected = codes.copy().reshape(-1)
    expected[[3, 19]] = [2, 1]
    assert np.array_equal(mirror.grid.codes.reshape(-1), expected)
    assert mirror.status["state"] == "exploring" and mirror.trail == [0.0, 0.0, 0.1, 0.2]
    assert mirror.three_state()[0, 3] == 100 and mirror.three_state()[3, 4] == 0
    assert mirror.apply(_delta(10, [1], [2])) == "gap"  # 9 was lost
    assert mirror.apply(_delta(11, [1], [2])) == "ignored"
    assert mirror.apply(_full(11, codes)) == "applied" and mirror.seq == 11
    assert mirror.apply(_delta(12, [1], [2], epoch=2)) == "gap"  # the grid was rebuilt meanwhile
    # what a joining viewer gets: the mirror as a full packet of its last sequence number
    rejoined = RobotMirror("copy")
    rejoined.apply(mirror.full_packet())
    assert rejoined.seq == mirror.seq and np.array_equal(rejoined.grid.codes, mirror.grid.codes)


def test_robot_names_are_one_key_chunk() -> None:
    assert keys.robot_name("", hostname="pi-4.local") == "pi-4"
    assert keys.robot_name("", hostname="my robot") == "my_robot"
    assert keys.robot_of("mazebot/alpha/packet") == "alpha"
    assert keys.robot_of("other/alpha/packet") is None
    with pytest.raises(ConfigError, match="robot_name"):
        keys.robot_name("", hostname="")
    with pytest.raises(ValueError, match="letters, digits"):
        ZenohConfig(robot_name="a/b")
    assert Config().zenoh.enabled is False  # off by default


def test_enabled_without_the_package_is_one_line_exit_69(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text("[zenoh]\nenabled = true\n")
    blocker = tmp_path / "zenoh.py"  # shadows the installed package: `import zenoh` fails as without the extra
    blocker.write_text("raise ImportError('no zenoh here')\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "XDG_STATE_HOME": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-m", "mazebot", "run", "--sim", "--config", str(config)],
                          capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 69
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'mazebot[zenoh]'" in lines[0]


def test_import_zenoh_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    from mazebot.fleet.session import import_zenoh

    monkeypatch.setitem(sys.modules, "zenoh", None)
    with pytest.raises(HardwareUnavailable, match=r"mazebot\[zenoh\]"):
        import_zenoh("mazebot watch")


# -- two robots in two processes ----------------------------------------------------------------


def _robot_config(folder: Path, name: str, zenoh_port: int) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(
        f'[web]\ncontrol_token = "{PIN}"\n[daemon]\nstate_dir = "{folder / name}"\n[persist]\nenabled = false\n'
        f'[zenoh]\nenabled = true\nrobot_name = "{name}"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n'
        "multicast_scouting = false\n"
    )
    return path


@pytest.fixture(scope="module")
def robots(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, dict[str, int]]]:
    folder = tmp_path_factory.mktemp("fleet")
    procs, ports, logs = [], {}, []
    env = {**os.environ, "XDG_STATE_HOME": str(folder)}
    for i, name in enumerate(NAMES):
        web_port, zenoh_port = unused_port(), unused_port()
        ports[name] = {"web": web_port, "zenoh": zenoh_port}
        config = _robot_config(folder, name, zenoh_port)
        logs.append((folder / f"{name}.log").open("w"))
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "mazebot", "run", "--sim", "--seed", str(i + 1), "--config", str(config),
             "--host", "127.0.0.1", "--port", str(web_port)],
            stdout=subprocess.DEVNULL, stderr=logs[-1], env=env))
    try:
        yield ports
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            try:
                assert proc.wait(timeout=15) == 0
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                raise
        for log in logs:
            log.close()


async def _until(predicate, timeout_s: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await asyncio.sleep(0.1)


async def _page_mirror(port: int, mirror: RobotMirror, stop: asyncio.Event) -> None:
    """The robot's own page, as a client: its packets applied to ``mirror``."""
    async with aiohttp.ClientSession() as http, http.ws_connect(f"http://127.0.0.1:{port}/ws") as ws:
        async for msg in ws:
            if msg.type == aiohttp.WSMsgType.BINARY:
                mirror.apply(msg.data)
            if stop.is_set():
                return


async def test_watcher_finds_both_robots_mirrors_their_maps_and_forwards_start_stop_with_the_pin(
        robots: dict[str, dict[str, int]]) -> None:
    from mazebot.fleet.session import open_session
    from mazebot.fleet.watch_app import create_watch_app
    from mazebot.fleet.watcher import Fleet

    endpoints = [f"tcp/127.0.0.1:{p['zenoh']}" for p in robots.values()]
    fleet = Fleet(open_session("test", "peer", endpoints, [], False))
    fleet.start()
    try:
        def walls(name: str) -> int:
            robot = fleet.robots.get(name)
            return 0 if robot is None or robot.grid is None else int(np.count_nonzero(robot.grid.codes == 2))

        # walls: a real map, not an empty grid
        await _until(lambda: all(walls(n) > 50 and fleet.robots[n].info for n in NAMES), 60,
                     "both robots' maps over Zenoh")
        assert {r.info["robot"] for r in fleet.robots.values()} == set(NAMES)

        # the map over Zenoh is the map on the robot's own page, cell for cell, at the same packet
        for name in NAMES:
            page = RobotMirror(name)
            stop = asyncio.Event()
            reader = asyncio.ensure_future(_page_mirror(robots[name]["web"], page, stop))
            zen = fleet.robots[name]
            seen: dict[int, np.ndarray] = {}

            def compare(zen: RobotMirror = zen, page: RobotMirror = page, seen: dict = seen) -> bool:
                if page.grid is not None and not page.waiting_full:
                    seen[page.seq] = page.grid.codes.copy()
                return zen.seq in seen and zen.grid is not None and not zen.waiting_full

            await _until(compare, 30, f"{name}: a packet seen on both the page and Zenoh")
            assert np.array_equal(zen.grid.codes, seen[zen.seq])
            stop.set()
            reader.cancel()
        maps = [fleet.robots[n].grid.codes for n in NAMES]
        assert maps[0].shape != maps[1].shape or not np.array_equal(*maps)  # two mazes, two maps

        # start/stop: the robot checks the PIN; a wrong one moves nothing
        alpha = fleet.robots["alpha"]
        wrong = await fleet.control("alpha", "start", "1357")
        assert wrong["ok"] is False and wrong["status"] == 403
        none = await fleet.control("alpha", "start", None)
        assert none["status"] == 401
        await asyncio.sleep(1.0)
        assert alpha.status["state"] == "idle"
        right = await fleet.control("alpha", "start", PIN)
        assert right["ok"] is True and right["status"] == 200
        await _until(lambda: alpha.status.get("state") == "exploring", 10, "alpha exploring")
        assert fleet.robots["beta"].status["state"] == "idle"  # only the robot asked

        # the watcher's page: the list, and alpha's phone page fed from Zenoh
        async with TestClient(TestServer(create_watch_app(fleet))) as client:
            listed = await (await client.get("/api/robots")).json()
            assert sorted(r["name"] for r in listed) == sorted(NAMES)
            assert "/robot/beta/" in await (await client.get("/")).text()
            assert (await client.get("/robot/alpha/")).status == 200
            assert (await client.get("/robot/nobody/")).status == 404
            ws = await client.ws_connect("/robot/alpha/ws")
            hello = await ws.receive_json(timeout=5)
            assert hello["type"] == "hello" and hello["robot"] == "alpha"
            viewer = RobotMirror("viewer")
            viewer.apply((await ws.receive(timeout=5)).data)
            assert viewer.grid is not None and viewer.status["state"] == "exploring"
            await ws.send_json({"type": "stop", "token": "0000"})
            while (reply := await ws.receive(timeout=5)).type != aiohttp.WSMsgType.TEXT:
                pass
            assert reply.json()["status"] == 403
            stop = await client.post("/robot/alpha/api/stop", headers={"X-Mazebot-Token": PIN})
            assert stop.status == 200
            await ws.close()
        await _until(lambda: alpha.status.get("state") == "stopped", 10, "alpha stopped")
    finally:
        fleet.close()
