"""The odometry task's one-pose composition gives exactly ``posegraph.compose``'s numbers."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from mazebot.geometry import compose
from mazebot.tasks.odometry_task import _compose


def test_scalar_compose_is_bit_identical_to_posegraph_compose() -> None:
    rng = np.random.default_rng(7)
    poses = rng.normal(0.0, 3.0, size=(5_000, 6))
    # headings on and around the wrap points, and exact zeros
    poses[:200, 2] = rng.choice([math.pi, -math.pi, 0.0, math.pi / 2, 2 * math.pi], 200)
    poses[200:400, 5] = -poses[200:400, 2] + rng.choice([math.pi, -math.pi, 0.0], 200)
    poses[400:500, :] = 0.0
    for a in poses:
        want = tuple(float(v) for v in compose(a[:3], a[3:]))
        got = _compose((a[0], a[1], a[2]), float(a[3]), float(a[4]), float(a[5]))
        assert got == want, (a, got, want)


def test_the_speed_loop_and_the_odometry_measure_a_tick_alike() -> None:
    """A calibrated wheel diameter ratio reaches the control loop's wheel speeds as well as the odometry."""
    from mazebot.config import Config
    from mazebot.slam.odometry import DiffDriveOdometry
    from mazebot.tasks.control_task import MotorControl

    config = Config()
    config.drive.wheel_diameter_ratio = 1.03
    d = config.drive
    odo = DiffDriveOdometry(config.encoders.ticks_per_rev, d.wheel_diameter_m, d.track_width_m, d.wheel_diameter_ratio)
    estimator = MotorControl.from_config(config).estimator
    assert estimator.metres_per_tick == (odo.metres_per_tick_left, odo.metres_per_tick_right)


def test_no_encoder_reading_yet_is_no_speed_not_a_zero_count() -> None:
    """Encoders that already counted (a restarted task) must not read as a jump from zero ticks."""
    from mazebot.config import Config
    from mazebot.state import SharedState
    from mazebot.tasks.control_task import MotorControl

    control = MotorControl.from_config(Config())
    state = SharedState()
    control.tick(state, 1.00)  # no reading yet
    state.wheel_ticks = (1.05, 5000, 5000)
    control.tick(state, 1.05)
    assert state.wheel_speeds_mps == (0.0, 0.0)
    state.wheel_ticks = (1.10, 5010, 5020)
    control.tick(state, 1.10)
    per_tick_m = control.estimator.metres_per_tick[0]
    smoothing = control.estimator.smoothing
    want = ((1 - smoothing) * 10 * per_tick_m / 0.05, (1 - smoothing) * 20 * per_tick_m / 0.05)
    assert state.wheel_speeds_mps == pytest.approx(want)


#: The quadrature levels (A, B) in the order a forward-turning wheel steps through them.
_GRAY = ((0, 0), (1, 0), (1, 1), (0, 1))


def _turn_edge(factory: Any, enc: Any, pins: tuple[Any, Any], step: list[int], time_s: float) -> None:
    """One encoder edge on each wheel of a turn on the spot (left backward, right forward), stamped ``time_s``.

    ``pins`` are the (A, B) pins of the left and the right wheel; ``step`` their places in
    :data:`_GRAY`, moved on.
    """
    wheels = ((pins[0], -1, enc.left_invert), (pins[1], 1, enc.right_invert))
    for k, (wheel_pins, direction, invert) in enumerate(wheels):
        sign = -direction if invert else direction
        new = (step[k] + sign) % 4
        old_levels, new_levels = _GRAY[step[k]], _GRAY[new]
        channel = 0 if old_levels[0] != new_levels[0] else 1
        factory.drive(wheel_pins[channel], new_levels[channel], time_s=time_s)
        step[k] = new


def test_the_pose_is_dated_by_the_edges_not_by_when_the_counts_were_read() -> None:
    """Under a CPU quota the encoder thread gets the edges in bursts; the history stays true.

    A wheel pair turning the robot on the spot at a steady rate; the edges reach the
    counters late and in bursts (nothing for 60 ms, then all until 30 ms ago). Every history
    entry must be the true pose at its time, to within a tick; the reading time (the old
    stamp) was 30 to 90 ms of turning late.
    """
    import asyncio

    from mazebot.config import Config
    from mazebot.io.encoders import WheelEncoders
    from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory
    from mazebot.slam.odometry import DiffDriveOdometry
    from mazebot.state import SharedState
    from mazebot.tasks import odometry_task

    config = Config()
    enc, drive = config.encoders, config.drive
    now = [0.0]
    factory = SimPinFactory(pin_class=BoundedHistoryPin, time_source=lambda: now[0])
    encoders = WheelEncoders.from_config(enc, factory)
    edges_per_s = 1000.0  # per wheel: left backward, right forward (a turn on the spot)
    left = (factory.pin(enc.left_a_pin), factory.pin(enc.left_b_pin))
    right = (factory.pin(enc.right_a_pin), factory.pin(enc.right_b_pin))
    start = 2 if enc.pull_up else 0  # the pins rest high with pull-ups
    step = [start, start]
    sent = [0.0]  # the time up to which the edges have been delivered

    def deliver(until_s: float) -> None:
        """Drive every edge that happened up to ``until_s``, each with its own stamp."""
        n = int(until_s * edges_per_s)
        while sent[0] < n:
            sent[0] += 1
            t = sent[0] / edges_per_s
            _turn_edge(factory, enc, (left, right), step, t)

    slept = asyncio.Event()

    class ManualClock:
        def now_s(self) -> float:
            return now[0]

        async def sleep(self, duration_s: float) -> None:
            now[0] += duration_s
            if int(now[0] / 0.06) != int((now[0] - duration_s) / 0.06):
                deliver(now[0] - 0.03)  # a burst every 60 ms: all that happened until 30 ms ago
            slept.set()
            await asyncio.sleep(0)

    state = SharedState()
    odometry = DiffDriveOdometry(enc.ticks_per_rev, drive.wheel_diameter_m, drive.track_width_m,
                                 drive.wheel_diameter_ratio)

    async def run_for(duration_s: float) -> None:
        task = asyncio.create_task(odometry_task.run(encoders, state, ManualClock(), enc, drive, odometry=odometry))
        while now[0] < duration_s:  # the manual clock moves only as the task sleeps on it
            await slept.wait()
            slept.clear()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    steps: list = []
    state.odometry_listeners = (steps.append,)  # what a recording writes: each reading, dated as the history
    with encoders:
        asyncio.run(run_for(1.0))
    per_tick_m = math.pi * drive.wheel_diameter_m / enc.ticks_per_rev
    true_rate_radps = 2 * edges_per_s * per_tick_m / drive.track_width_m  # each wheel's edges are ticks (x4)
    history = state.odometry_history
    span = history.span_s
    assert span is not None
    times = np.linspace(max(span[0], 0.1), span[1], 50)
    _, _, theta = history.at(times)
    tick_rad = 2 * per_tick_m / drive.track_width_m
    assert np.max(np.abs(theta - true_rate_radps * times)) <= 2 * tick_rad
    # dated by the reading time the same history would be 60 ms of turning behind at worst
    assert 0.06 * true_rate_radps > 10 * tick_rad
    ages = np.asarray(state.odometry_edge_age_ms)
    assert ages.min() >= 29.0  # the bursts were late indeed
    # the listeners heard every reading with the date the history got (None: not added), so a
    # replay of a recording builds this same history
    dated = [step.pose_time_s for step in steps if step.pose_time_s is not None]
    assert len(dated) == len(history) and (dated[0], dated[-1]) == span
    assert any(step.pose_time_s is None for step in steps)
    assert all(step.pose_time_s is None or step.pose_time_s <= step.reading_time_s for step in steps)


def test_a_reading_without_new_edges_holds_the_pose_only_once_the_wheels_rest() -> None:
    """No new edge: late edges while the motors drive (nothing added), a rest once braked (now)."""
    from mazebot.slam.ekf import OdometryHistory
    from mazebot.tasks.odometry_task import REST_AFTER_S, STILL_WHEN_DRIVEN_S, _pose_time_s

    history = OdometryHistory(3.0)
    history.append(10.0, 0.0, 0.0, 0.0)
    assert _pose_time_s(10.5, 0.02, True, history, braked_s=0.0) == 10.48  # new edges: the newest one's stamp
    assert _pose_time_s(10.5, None, False, history) == 10.5  # no usable stamp: the reading's time
    late = REST_AFTER_S + 0.1
    assert _pose_time_s(10.5, late, False, history, braked_s=0.0) is None  # driven: the edges may be late
    assert _pose_time_s(10.5, late, False, history, braked_s=late) == 10.5  # braked and still: at rest
    assert _pose_time_s(10.5, 0.05, False, history, braked_s=late) is None  # braked a moment ago: may coast
    assert _pose_time_s(12.0, STILL_WHEN_DRIVEN_S, False, history, braked_s=0.0) == 12.0  # driven, never turning
    assert _pose_time_s(10.5, 0.6, True, history, braked_s=0.0) == 10.0  # never before the newest entry


def test_the_brake_is_dated_by_the_control_loops_write_not_by_a_late_reading() -> None:
    """A reading 0.3 s after the one before (a starved process) finds the throttles at 0: the motors were
    braked 20 ms before it, not since the reading before, and their last edges may still be on their way."""
    from mazebot.slam.ekf import OdometryHistory
    from mazebot.tasks.odometry_task import REST_AFTER_S, BrakedSince, _pose_time_s

    brakes = BrakedSince()
    assert brakes.update([], fallback_s=4.0) == 4.0  # no write seen: the readings' rule
    writes = [(10.0 + 0.05 * k, 0.4, 0.4) for k in range(6)]  # driving until 10.25
    assert brakes.update(writes, fallback_s=10.0) == math.inf  # driven
    writes += [(10.28, 0.0, 0.0), (10.33, 0.0, 0.0)]
    braked_since_s = brakes.update(writes, fallback_s=10.0)
    assert braked_since_s == 10.28
    history = OdometryHistory(3.0)
    history.append(10.0, 0.0, 0.0, 0.0)
    late = REST_AFTER_S + 0.05  # the edge thread starved too
    assert _pose_time_s(10.3, late, False, history, braked_s=10.3 - braked_since_s) is None  # may coast: wait
    assert _pose_time_s(10.3, late, False, history, braked_s=10.3 - 10.0) == 10.3  # the readings' rule: "at rest"
    writes += [(10.38, 0.0, 0.0), (10.6, 0.0, 0.0)]
    assert brakes.update(writes, fallback_s=10.0) == 10.28  # still braked since the first 0
    writes.append((10.65, 0.0, 0.2))
    assert brakes.update(writes, fallback_s=10.0) == math.inf


def test_a_turn_that_begins_while_the_readings_are_late_is_in_the_history_where_it_began() -> None:
    """The odometry read every 0.25 s (a starved loop) still holds the turn's start where it was.

    The robot stands for 0.6 s, then turns on the spot at a steady rate; every edge reaches the
    counters at once with its own stamp, but the odometry task reads only every 0.25 s. The
    history must give the true heading at every moment to within a few ticks; with a pose only
    at each reading, the turn's start was smeared over the gap (the same history interpolated
    between its readings: degrees off).
    """
    import asyncio

    from mazebot.config import Config
    from mazebot.io.encoders import WheelEncoders
    from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory
    from mazebot.slam.odometry import DiffDriveOdometry
    from mazebot.state import SharedState
    from mazebot.tasks import odometry_task

    config = Config()
    enc, drive = config.encoders, config.drive
    now = [0.0]
    factory = SimPinFactory(pin_class=BoundedHistoryPin, time_source=lambda: now[0])
    encoders = WheelEncoders.from_config(enc, factory)
    edges_per_s, turn_from_s = 1000.0, 0.6  # per wheel once turning (between two readings): left back, right on
    left = (factory.pin(enc.left_a_pin), factory.pin(enc.left_b_pin))
    right = (factory.pin(enc.right_a_pin), factory.pin(enc.right_b_pin))
    start = 2 if enc.pull_up else 0  # the pins rest high with pull-ups
    step = [start, start]
    sent = [0]

    def deliver(until_s: float) -> None:
        """Drive every edge of the turn up to ``until_s``, each with its own stamp."""
        n = int(max(0.0, until_s - turn_from_s) * edges_per_s)
        while sent[0] < n:
            sent[0] += 1
            t = turn_from_s + sent[0] / edges_per_s
            _turn_edge(factory, enc, (left, right), step, t)

    slept = asyncio.Event()

    class StarvedClock:
        """Each sleep of the task lasts 0.25 s: the loop gets to the odometry four times a second."""

        def now_s(self) -> float:
            return now[0]

        async def sleep(self, duration_s: float) -> None:
            now[0] += max(duration_s, 0.25)
            deliver(now[0])
            slept.set()
            await asyncio.sleep(0)

    state = SharedState()
    odometry = DiffDriveOdometry(enc.ticks_per_rev, drive.wheel_diameter_m, drive.track_width_m,
                                 drive.wheel_diameter_ratio)

    async def run_for(duration_s: float) -> None:
        task = asyncio.create_task(odometry_task.run(encoders, state, StarvedClock(), enc, drive, odometry=odometry))
        while now[0] < duration_s:
            await slept.wait()
            slept.clear()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    steps: list = []
    state.odometry_listeners = (steps.append,)
    with encoders:
        asyncio.run(run_for(1.6))
    per_tick_m = math.pi * drive.wheel_diameter_m / enc.ticks_per_rev
    rate_radps = 2 * edges_per_s * per_tick_m / drive.track_width_m
    history = state.odometry_history
    span = history.span_s
    assert span is not None and span[1] > 1.2
    times = np.linspace(turn_from_s - 0.2, span[1], 200)
    _, _, theta = history.at(times)
    truth = rate_radps * np.clip(times - turn_from_s, 0.0, None)
    tick_rad = 2 * per_tick_m / drive.track_width_m
    assert np.max(np.abs(theta - truth)) <= 0.01 * rate_radps + 2 * tick_rad  # one sample period of turning
    assert 0.25 * rate_radps > 20 * tick_rad  # a pose only per reading would be far off at the start
    # the listeners heard every pose the history got, with its date
    dated = [s.pose_time_s for s in steps if s.pose_time_s is not None]
    assert len(dated) == len(history) and (dated[0], dated[-1]) == span
