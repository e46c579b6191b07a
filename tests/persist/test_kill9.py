"""A daemon killed with SIGKILL mid-run leaves its last saved map on disk, and a restart serves it.

Real processes: ``mazebot run --sim`` on a free port with a temporary state directory,
started by the page's API, killed with ``kill -9`` (no handler, no last save) while
exploring and saving every second, then started again with ``--resume latest``.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import numpy as np
import pytest
from aiohttp.test_utils import unused_port

from mazebot.persist.runs import find_run
from mazebot.persist.snapshot import load_run

pytestmark = pytest.mark.slow  # real daemon processes killed and restarted


def _config(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(
        # a busy test machine can starve the simulator for a moment: a lidar gap must not end the run
        f'[daemon]\nstate_dir = "{tmp_path / "state"}"\nauto_resume = true\nlidar_silence_s = 1.5\n'
        f'[web]\nhost = "127.0.0.1"\nport = {port}\ncontrol_token = "246810"\n'
        "[persist]\nsave_period_s = 1.0\n",
        encoding="utf-8",
    )
    return path


async def _request(method: str, port: int, path: str, **kwargs) -> tuple[int, bytes]:
    async with aiohttp.ClientSession() as session, session.request(
        method, f"http://127.0.0.1:{port}{path}", timeout=aiohttp.ClientTimeout(total=5), **kwargs
    ) as response:
        return response.status, await response.read()


def _wait(condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"{what} within {timeout_s} s"
        time.sleep(0.1)


def _served(port: int) -> bool:
    try:
        return asyncio.run(_request("GET", port, "/api/status"))[0] == 200
    except (aiohttp.ClientError, OSError, TimeoutError):
        return False


def _pgm(data: bytes) -> np.ndarray:
    """A binary PGM (P5) as an array: magic, comment lines, size, maximum, pixels."""
    header: list[bytes] = []
    rest = data
    while len(header) < 4:
        line, rest = rest.split(b"\n", 1)
        if not line.startswith(b"#"):
            header += line.split()
    assert header[0] == b"P5" and header[3] == b"255"
    cols, rows = int(header[1]), int(header[2])
    return np.frombuffer(rest, dtype=np.uint8, count=rows * cols).reshape(rows, cols)


def _start(config: Path, port: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "mazebot", "run", "--sim", "--config", str(config), "--port", str(port), *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )


def test_kill_9_mid_run_then_restart_serves_the_last_saved_map(tmp_path: Path) -> None:
    port = unused_port()
    config = _config(tmp_path, port)
    runs = tmp_path / "state" / "runs"
    proc = _start(config, port)
    try:
        _wait(lambda: _served(port), 15, "the daemon serves")
        status, _ = asyncio.run(_request("POST", port, "/api/start", headers={"X-Mazebot-Token": "246810"}))
        assert status == 200

        def saved_twice() -> bool:
            # a few keyframes and a map of more than the start (a slow machine saves the first ones early)
            metas = list(runs.glob("*/meta.json"))
            if not metas or json.loads(metas[0].read_text())["keyframes"] < 8:
                return False
            pgm = metas[0].parent / "map.pgm"
            return pgm.exists() and int((_pgm(pgm.read_bytes()) != 205).sum()) > 1000
        _wait(saved_twice, 60, "the run is saved with a few keyframes and a map")
        state = json.loads(asyncio.run(_request("GET", port, "/api/status"))[1])
        assert state["state"] == "exploring"  # killed mid-run, not at rest
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=10) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        proc.stderr.close()

    # what is on disk is a complete run: every file reads, the graph matches the keyframes
    run_dir = find_run(runs, "latest")
    saved = load_run(run_dir)
    assert len(saved.keyframes) >= 8 and not list(run_dir.glob(".*.tmp"))  # no half-written file left behind
    saved_pgm = _pgm((run_dir / "map.pgm").read_bytes())

    proc = _start(config, port, "--resume", "latest")
    try:
        _wait(lambda: _served(port), 15, "the restarted daemon serves")
        status, body = asyncio.run(_request("GET", port, "/map.pgm"))
        assert status == 200
        served = _pgm(body)
        # the served map is the saved one (the resumed robot may have added a revolution or two to it)
        assert served.shape == saved_pgm.shape
        known = saved_pgm != 205
        assert known.sum() > 1000
        assert np.mean(served[known] == saved_pgm[known]) > 0.98
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=15) == 0
        assert "Traceback" not in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
        proc.stderr.close()
