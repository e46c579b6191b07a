"""The whole daemon on the simulated robot: starts, serves, faults safely, stops on signals."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import aiohttp
import pytest
from aiohttp.test_utils import unused_port

from mazebot.config import Config
from mazebot.main import Hardware, run_daemon
from mazebot.sim.backend import sim_hardware_builder
from mazebot.state import RunState, SharedState
from mazebot.tasks.supervisor import Supervisor

CONTROL_TOKEN = "2468"


def _config(port: int) -> Config:
    config = Config()
    config.web.host = "127.0.0.1"
    config.web.port = port
    config.web.control_token = CONTROL_TOKEN
    return config


async def _get_status(port: int) -> dict:
    async with aiohttp.ClientSession() as session, session.get(f"http://127.0.0.1:{port}/api/status") as resp:
        assert resp.status == 200
        return await resp.json()


async def test_daemon_runs_the_real_drivers_on_the_simulated_robot() -> None:
    port = unused_port()
    ready = asyncio.Event()
    started: dict[str, object] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state, sup=sup)

    daemon = asyncio.create_task(
        run_daemon(_config(port), sim_hardware_builder(), ready=ready, install_signal_handlers=False,
                   on_started=on_started, autonomous=False)
    )
    await asyncio.wait_for(ready.wait(), 10)
    state: SharedState = started["state"]  # type: ignore[assignment]
    hw: Hardware = started["hw"]  # type: ignore[assignment]
    # a few revolutions come through the emulator, the byte stream and the real driver
    for _ in range(100):
        if state.sensors.lidar_revolutions >= 3:
            break
        await asyncio.sleep(0.1)
    status = await _get_status(port)
    assert status["state"] == "idle"
    assert status["sensors"]["lidar_revolutions"] >= 3
    assert status["sensors"]["lidar_bytes_dropped"] == 0
    assert state.latest_scan is not None and state.latest_scan.valid.sum() > 100

    # start: the control task may now apply commands; stop: zero at once
    async with aiohttp.ClientSession() as session:
        async with session.post(f"http://127.0.0.1:{port}/api/start", headers={"X-Mazebot-Token": "0000"}) as resp:
            assert resp.status == 403  # a wrong PIN moves nothing
        async with session.post(f"http://127.0.0.1:{port}/api/start",
                                headers={"X-Mazebot-Token": CONTROL_TOKEN}) as resp:
            assert resp.status == 200
        await asyncio.sleep(0.1)
        assert state.run_state is RunState.EXPLORING
        state.throttle_command = (0.5, 0.5, asyncio.get_running_loop().time() + 10.0)
        await asyncio.sleep(0.3)
        assert state.sensors.encoder_ticks_left > 0  # the wheels turned and the encoders counted
        async with session.post(f"http://127.0.0.1:{port}/api/stop",
                                headers={"X-Mazebot-Token": CONTROL_TOKEN}) as resp:
            assert resp.status == 200
        await asyncio.sleep(0.1)
    assert state.run_state is RunState.STOPPED
    kit = hw.sim.kit
    assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0

    started["sup"].request_stop("test over")  # type: ignore[union-attr]
    assert await asyncio.wait_for(daemon, 10) == 0


async def test_a_crashing_task_stops_the_motors_and_the_daemon_keeps_serving() -> None:
    port = unused_port()
    ready = asyncio.Event()
    started: dict[str, object] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state, sup=sup)

        async def broken() -> None:
            await asyncio.sleep(0.2)
            raise ValueError("matrix not positive definite")

        state.run_state = RunState.EXPLORING
        hw.motors.set(0.4, 0.4)
        sup.start("planner", broken)

    daemon = asyncio.create_task(
        run_daemon(_config(port), sim_hardware_builder(), ready=ready, install_signal_handlers=False,
                   on_started=on_started, autonomous=False)
    )
    await asyncio.wait_for(ready.wait(), 10)
    await asyncio.sleep(0.5)
    status = await _get_status(port)
    assert status["state"] == "fault"
    assert status["fault"]["source"] == "planner"
    assert "ValueError: matrix not positive definite" in status["fault"]["message"]
    kit = started["hw"].sim.kit  # type: ignore[union-attr]
    assert kit.motor1.throttle == 0.0 and kit.motor2.throttle == 0.0
    assert not daemon.done()
    started["sup"].request_stop("test over")  # type: ignore[union-attr]
    assert await asyncio.wait_for(daemon, 10) == 0


async def test_sigterm_zeroes_the_motors_within_100_ms_and_exits_0() -> None:
    port = unused_port()
    ready = asyncio.Event()
    started: dict[str, object] = {}

    def on_started(hw: Hardware, state: SharedState, sup: Supervisor) -> None:
        started.update(hw=hw, state=state)
        state.run_state = RunState.EXPLORING
        state.throttle_command = (0.6, 0.6, asyncio.get_running_loop().time() + 60.0)

    daemon = asyncio.create_task(run_daemon(_config(port), sim_hardware_builder(), ready=ready, on_started=on_started,
                                            autonomous=False))
    await asyncio.wait_for(ready.wait(), 10)
    await asyncio.sleep(0.2)
    kit = started["hw"].sim.kit  # type: ignore[union-attr]
    assert kit.motor1.throttle != 0.0  # driving
    loop = asyncio.get_running_loop()
    sent_s = loop.time()
    os.kill(os.getpid(), signal.SIGTERM)
    assert await asyncio.wait_for(daemon, 10) == 0
    stops = [w for w in kit.command_log if w.throttle == 0.0 and w.time_s >= sent_s]
    assert stops, "no stop written after SIGTERM"
    assert stops[0].time_s - sent_s < 0.1


def test_run_sim_serves_within_5_s_and_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    port = unused_port()
    t0 = time.monotonic()
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path)}  # the generated PIN goes here, not to ~
    proc = subprocess.Popen([sys.executable, "-m", "mazebot", "run", "--sim", "--host", "127.0.0.1",
                             "--port", str(port)], stderr=subprocess.PIPE, text=True, env=env)
    try:
        served = False
        while time.monotonic() - t0 < 5.0 and not served:
            try:
                served = asyncio.run(_get_status(port))["version"] is not None
            except aiohttp.ClientError:
                time.sleep(0.1)
        assert served, "nothing served on the port within 5 s"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
        stderr = proc.stderr.read()
        assert "Traceback" not in stderr
        token = (tmp_path / "mazebot" / "control_token").read_text().strip()
        assert stderr.count(token) == 1  # the generated PIN is logged once, on first start
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()


def test_real_run_without_hardware_exits_69_naming_the_device() -> None:
    proc = subprocess.run([sys.executable, "-m", "mazebot", "run"], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 69
    lines = proc.stderr.strip().splitlines()
    assert lines[-1].startswith("mazebot: motor HAT not found at I2C address 0x60")
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("argv", [["run", "--seed", "3"], ["run", "--sim", "--size", "1x99"]])
def test_bad_run_arguments_exit_2(argv: list[str]) -> None:
    proc = subprocess.run([sys.executable, "-m", "mazebot", *argv], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
