"""The progress the page charts comes from the robot: ``distance_m`` (this exploration's odometry
path length) beside ``coverage`` and ``elapsed_s``, in the packets and in ``/api/status``."""

from __future__ import annotations

import pytest

from mazebot.slam.odometry import DiffDriveOdometry
from mazebot.state import RunState, SharedState
from mazebot.tasks.command_task import apply_command
from mazebot.web.app import WebSettings, create_app
from mazebot.web.broadcaster import Broadcaster
from mazebot.web.protocol import decode_packet


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def now_s(self) -> float:
        return self.t

    def __call__(self) -> float:
        return self.t


class Motors:
    def stop(self) -> None:
        pass


def _drive(odo: DiffDriveOdometry, left_m: float, right_m: float) -> None:
    ticks = (round(left_m / odo.metres_per_tick), round(right_m / odo.metres_per_tick))
    last = odo._last or (0, 0)
    odo.update(last[0] + ticks[0], last[1] + ticks[1])


def _last_status(b: Broadcaster, viewer) -> dict:
    packets = [p for p in viewer.pending() if isinstance(p, bytes)]
    viewer._items.clear()
    merged: dict = {}
    for p in packets:
        merged.update(decode_packet(p).status)
    return merged


def test_distance_counts_from_each_new_exploration_and_a_resume_keeps_counting() -> None:
    state, clock = SharedState(), Clock()
    odo = DiffDriveOdometry(ticks_per_rev=1440, wheel_diameter_m=0.065, track_width_m=0.15)
    odo.update(0, 0)
    state.odometry = odo.pose
    assert state.run_distance_m() is None  # no run yet: nothing to count
    _drive(odo, 0.5, 0.5)  # pushed by hand before any start: not part of a run
    apply_command("start", state, Motors(), clock)
    assert state.run_distance_m() == pytest.approx(0.0)
    _drive(odo, 1.0, 1.0)
    _drive(odo, 0.2, -0.2)  # turning on the spot: the axle centre does not move
    assert state.run_distance_m() == pytest.approx(1.0, abs=1e-3)
    apply_command("stop", state, Motors(), clock)
    apply_command("start", state, Motors(), clock)  # resumes the same exploration
    _drive(odo, 0.25, 0.25)
    assert state.run_distance_m() == pytest.approx(1.25, abs=1e-3)
    state.run_state = RunState.DONE
    apply_command("start", state, Motors(), clock)  # from done: a new exploration
    assert state.run_distance_m() == pytest.approx(0.0)
    _drive(odo, -0.3, -0.3)  # reversing counts as driving
    assert state.run_distance_m() == pytest.approx(0.3, abs=1e-3)


def test_packets_carry_distance_coverage_and_elapsed_for_the_chart() -> None:
    state, clock = SharedState(), Clock()
    odo = DiffDriveOdometry(ticks_per_rev=1440, wheel_diameter_m=0.065, track_width_m=0.15)
    odo.update(0, 0)
    state.odometry = odo.pose
    b = Broadcaster(state, now_s=clock)
    viewer = b.add(None, "phone")  # type: ignore[arg-type]
    assert _last_status(b, viewer)["distance_m"] is None
    apply_command("start", state, Motors(), clock)
    samples = []
    for step in range(1, 6):
        clock.t += 1.0
        _drive(odo, 0.1, 0.1)
        state.coverage = 0.1 * step
        b.tick()
        s = _last_status(b, viewer)
        samples.append((s["elapsed_s"], s["coverage"], s["distance_m"]))
    assert samples == [(pytest.approx(float(k)), pytest.approx(0.1 * k), pytest.approx(0.1 * k, abs=0.01))
                       for k in range(1, 6)]


async def test_api_status_has_distance_m(aiohttp_client) -> None:
    state, clock = SharedState(), Clock()
    odo = DiffDriveOdometry(ticks_per_rev=1440, wheel_diameter_m=0.065, track_width_m=0.15)
    odo.update(0, 0)
    state.odometry = odo.pose
    client = await aiohttp_client(create_app(state, settings=WebSettings(control_token="2468", broadcast_hz=0)))
    assert (await (await client.get("/api/status")).json())["distance_m"] is None
    apply_command("start", state, Motors(), clock)
    _drive(odo, 0.42, 0.42)
    assert (await (await client.get("/api/status")).json())["distance_m"] == pytest.approx(0.42, abs=1e-3)
