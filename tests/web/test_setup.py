"""The setup view's server side on aiohttp's real server: raw scan, jog with the PIN only while the
robot is not running, a stale jog stopping in the control task, the doctor's non-motor checks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from aiohttp import web

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.io.scan import Scan
from mazebot.state import RunState, SharedState
from mazebot.tasks.control_task import MotorControl
from mazebot.web.app import WebSettings, create_app
from mazebot.web.setup import JOG_MAX_THROTTLE

TOKEN = "4321"


@pytest.fixture
def state() -> SharedState:
    return SharedState()


def _app(state: SharedState, tmp_path: Path) -> web.Application:
    return create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0), state_dir=tmp_path)


def _scan(n: int = 360) -> Scan:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ranges = np.full(n, 0.6)
    valid = np.ones(n, bool)
    valid[::4] = False
    ranges[~valid] = 0.0
    return Scan(angles, ranges, np.full(n, 40, np.uint8), np.zeros(n), valid, revolution=7)


async def test_setup_shows_the_raw_revolution_and_the_wheels(aiohttp_client, state, tmp_path) -> None:
    client = await aiohttp_client(_app(state, tmp_path))
    body = await (await client.get("/api/setup")).json()
    assert body["scan"] is None and body["jog_refused"] is None
    state.latest_scan = _scan()
    state.sensors.encoder_ticks_left = 123
    body = await (await client.get("/api/setup")).json()
    assert body["scan"]["samples"] == 360 and body["scan"]["valid"] == 270
    assert len(body["scan"]["angle_rad"]) == 270 and set(body["scan"]["range_m"]) == {0.6}
    assert body["encoders"]["left_ticks"] == 123


async def test_jog_needs_the_pin(aiohttp_client, state, tmp_path) -> None:
    client = await aiohttp_client(_app(state, tmp_path))
    assert (await client.post("/api/jog", json={"left": 0.3, "right": 0.3})).status == 401
    wrong = await client.post("/api/jog", json={"left": 0.3, "right": 0.3}, headers={"X-Mazebot-Token": "0000"})
    assert wrong.status == 403
    assert state.jog_command is None


async def test_jog_is_clamped_and_refused_while_a_run_is_going_or_a_fault_is_active(
    aiohttp_client, state, tmp_path
) -> None:
    client = await aiohttp_client(_app(state, tmp_path))
    pin = {"X-Mazebot-Token": TOKEN}
    ok = await client.post("/api/jog", json={"left": 1.0, "right": -0.2}, headers=pin)
    assert ok.status == 200
    left, right, _ = state.jog_command
    assert (left, right) == (JOG_MAX_THROTTLE, -0.2)
    for run_state in (RunState.EXPLORING, RunState.RETURNING, RunState.FAULT):
        state.run_state = run_state
        refused = await client.post("/api/jog", json={"left": 0.2, "right": 0.2}, headers=pin)
        assert refused.status == 409
        assert state.jog_command is None
    state.run_state = RunState.IDLE
    assert (await client.post("/api/jog", json={"left": "x", "right": 0}, headers=pin)).status == 400
    assert (await client.post("/api/jog", json={"left": float("nan"), "right": 0}, headers=pin)).status == 400
    await client.post("/api/jog", json={"left": 0.2, "right": 0.2}, headers=pin)
    await client.post("/api/jog", json={"left": 0, "right": 0}, headers=pin)  # a release
    assert state.jog_command is None


def test_the_control_task_drives_a_fresh_jog_and_stops_a_stale_one(state) -> None:
    config = Config()
    control = MotorControl.from_config(config)
    now_s = RealClock().now_s()
    state.jog_command = (0.3, -0.3, now_s)
    assert control.tick(state, now_s + 0.05) == (0.3, -0.3)
    ttl_s = config.motors.command_ttl_s
    assert control.tick(state, now_s + ttl_s + 0.01) == (0.0, 0.0)  # not refreshed: the page is gone
    state.jog_command = (0.3, 0.3, now_s + 1.0)
    state.run_state = RunState.EXPLORING  # a run started meanwhile: the planner drives, never a jog
    assert control.tick(state, now_s + 1.05) == (0.0, 0.0)
    state.run_state = RunState.FAULT
    assert control.tick(state, now_s + 1.1) == (0.0, 0.0)


async def test_doctor_endpoint_runs_the_checks_that_move_nothing(aiohttp_client, state, tmp_path) -> None:
    client = await aiohttp_client(_app(state, tmp_path))
    checks = (await (await client.get("/api/doctor")).json())["checks"]
    by_part = {c["part"]: c for c in checks}
    assert {"power", "CPU temperature", "free space", "clock", "lidar revolution", "motors and encoders"} <= set(
        by_part)
    assert by_part["lidar revolution"]["status"] == "FAIL"  # no revolution yet
    assert by_part["motors and encoders"]["status"] == "skip"
    state.latest_scan = _scan()
    checks = (await (await client.get("/api/doctor")).json())["checks"]
    assert {c["part"]: c["status"] for c in checks}["lidar revolution"] == "ok"
