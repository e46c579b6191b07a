"""The simulated robot behind the real drivers: motor driver → physics → encoder edges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mazebot.clock import RealClock
from mazebot.config import Config
from mazebot.io.encoders import WheelEncoders
from mazebot.io.motors import DifferentialMotors
from mazebot.sim.maze_generator import generate_maze
from mazebot.sim.robot import SimulatedRobot
from mazebot.sim.world import World, world_from_layout


def _open_world() -> World:
    # a 4x4 braided maze; the robot only spins in place in these tests
    return world_from_layout(generate_maze(4, 4, seed=2, kind="rooms"))


@pytest.mark.parametrize("decoding", ["x1", "x2", "x4"])
def test_encoder_ticks_match_true_wheel_rotation(decoding: str) -> None:
    config = Config()
    config.encoders.decoding = decoding
    config.sim.slip_std = 0.0
    robot = SimulatedRobot(_open_world(), config, seed=1)
    encoders = WheelEncoders.from_config(config.encoders, robot.pin_factory)
    motors = DifferentialMotors.from_config(config.motors, robot.kit, RealClock(), loop=None)
    try:
        robot.step(0.0)
        motors.set(-0.5, 0.5)  # spin in place: no walls touched
        t = 0.0
        for _ in range(300):
            t += 0.005
            robot.step(t)
        reading = encoders.read()
        left_rad, right_rad = robot.physics.wheel_angle_rad
        per_rad = config.encoders.ticks_per_rev / math.tau
        # one tick of quantisation, nothing else: every edge was counted
        assert reading.left_ticks == pytest.approx(left_rad * per_rad, abs=1.0)
        assert reading.right_ticks == pytest.approx(right_rad * per_rad, abs=1.0)
        assert reading.left_ticks < 0 < reading.right_ticks  # left backwards, right forwards
        assert reading.invalid_transitions == 0
    finally:
        motors.close()
        encoders.close()
        robot.close()


def test_inverted_wiring_is_what_the_config_corrects() -> None:
    # right motor mounted mirrored (motors.right_invert) and right encoder counting
    # backwards (encoders.right_invert): driving forward must move forward and count up.
    config = Config()
    config.sim.slip_std = 0.0
    assert config.motors.right_invert and config.encoders.right_invert
    world = world_from_layout(generate_maze(2, 6, seed=0, kind="perfect"))
    robot = SimulatedRobot(world, config, seed=1)
    encoders = WheelEncoders.from_config(config.encoders, robot.pin_factory)
    motors = DifferentialMotors.from_config(config.motors, robot.kit, RealClock(), loop=None)
    try:
        x0, y0, th0 = robot.physics.pose
        robot.step(0.0)
        motors.set(0.4, 0.4)
        for i in range(1, 41):
            robot.step(i * 0.005)
        motors.stop()
        x1, y1, _ = robot.physics.pose
        heading = np.array([math.cos(th0), math.sin(th0)])
        assert float(np.dot([x1 - x0, y1 - y0], heading)) > 0.01
        reading = encoders.read()
        assert reading.left_ticks > 0 and reading.right_ticks > 0
        assert robot.kit.motor2.throttle == 0.0
    finally:
        motors.close()
        encoders.close()
        robot.close()


def test_pose_history_feeds_the_lidar_at_sample_times() -> None:
    config = Config()
    robot = SimulatedRobot(_open_world(), config, seed=1)
    try:
        robot.step(0.0)
        robot.kit.motor1.throttle = -0.5
        robot.kit.motor2.throttle = -0.5  # right wired mirrored: this spins left
        for i in range(1, 101):
            robot.step(i * 0.005)
        robot.lidar_head.restart(0.0)
        samples = robot.lidar_head.advance(0.5, robot.poses)
        assert 900 <= len(samples) <= 1100  # 5.5 rev/s x 360 samples/rev x 0.5 s, rate jitter 3%
        assert np.all(np.diff(samples.time_s) > 0)
        assert samples.start.sum() in (2, 3)  # revolutions begin at 0 deg
    finally:
        robot.close()


def test_encoder_pins_keep_a_bounded_edge_history() -> None:
    # gpiozero's MockPin appends every edge to pin.states; over a long simulation that
    # list was hundreds of megabytes. The simulator's pins keep only the recent edges.
    config = Config()
    robot = SimulatedRobot(_open_world(), config, seed=1)
    encoders = WheelEncoders.from_config(config.encoders, robot.pin_factory)
    try:
        robot.step(0.0)
        robot.kit.motor1.throttle = robot.kit.motor2.throttle = 0.6
        t = 0.0
        for _ in range(200):
            t += 0.01
            robot.step(t)
        assert robot.left_signal.edges > 1000
        pin = robot.pin_factory.pin(config.encoders.left_a_pin)
        assert len(pin.states) <= 64
        assert pin.states[-1].state == pin.state  # the history still ends at the current level
        assert encoders.read().invalid_transitions == 0
    finally:
        encoders.close()
        robot.close()


def lidar_lead_over_physics(robot: SimulatedRobot) -> list[float]:
    """From now on, how far each batch of the robot's lidar samples lies past its last physics step (s)."""
    ahead_s: list[float] = []
    advance = robot.lidar_head.advance

    def checked_advance(now_s: float, poses):  # type: ignore[no-untyped-def]
        samples = advance(now_s, poses)
        if len(samples):
            ahead_s.append(float(samples.time_s.max()) - float(robot.time_s))
        return samples

    robot.lidar_head.advance = checked_advance  # type: ignore[method-assign]
    return ahead_s


def test_the_robot_tick_paces_the_lidar_from_poses_already_reached() -> None:
    """The daemon's wiring: the robot's tick has the emulator send, and the real driver decodes it.

    Every sample the head measures lies at or before the last physics step, so its pose is
    interpolated between true poses (on its own timer the emulator could run up to one tick
    past the physics and hold the last pose), and the revolutions come through whole.
    """
    import asyncio
    import contextlib

    from mazebot.io.rplidar import RPLidar
    from mazebot.sim.backend import SimLidarLine
    from mazebot.sim.lidar_emulator import RPLidarEmulator
    from mazebot.sim.virtual_time import run_virtual

    config = Config()
    robot = SimulatedRobot(_open_world(), config, seed=4)
    robot.kit.motor1.throttle, robot.kit.motor2.throttle = 0.5, -0.5  # spin in place
    clock = RealClock()
    emulator = RPLidarEmulator(robot.lidar_head, robot.poses, clock, self_paced=False)
    robot.attach_lidar(emulator)
    ahead_s = lidar_lead_over_physics(robot)

    async def run() -> list[int]:
        sim = asyncio.create_task(robot.run(clock))
        line = SimLidarLine(emulator)
        sizes: list[int] = []
        try:
            async with RPLidar(line.connect, clock, spin_up_s=0.1) as lidar:
                scans = lidar.scans()
                async with contextlib.aclosing(scans):  # type: ignore[type-var]
                    async for scan in scans:
                        sizes.append(len(scan.range_m))
                        if len(sizes) == 8:
                            break
        finally:
            sim.cancel()
            await line.close()
        return sizes

    sizes = run_virtual(asyncio.wait_for(run(), 60.0))
    assert len(ahead_s) > 50  # one send every other tick for ~1.5 s
    assert max(ahead_s) <= 0.0
    per_rev = robot.lidar_head.params.samples_per_rev
    assert all(abs(n - per_rev) <= 0.05 * per_rev for n in sizes)  # whole revolutions (±3 % jitter)


def test_a_lidar_on_its_own_timer_steps_the_world_before_it_measures_wherever_it_is_built() -> None:
    """Every world that serves a lidar builds it with ``make_lidar`` (the daemon's backend, the
    CPU-quota bench's world process, the doctor): on its own timer (the default) the emulator
    sends every few milliseconds between the robot's 10 ms ticks, and it used to measure those
    samples from the last pose the physics had reached while the robot spun on. Now it steps the
    world first, and the step's own hook (the world process sends its encoder edges there) runs."""
    import asyncio
    import contextlib

    from mazebot.io.rplidar import RPLidar
    from mazebot.io.rplidar_models import MODELS
    from mazebot.sim.backend import SimLidarLine
    from mazebot.sim.virtual_time import run_virtual

    config = Config()
    assert not config.sim.lidar_paced_by_robot  # the default this test is about
    robot = SimulatedRobot(_open_world(), config, seed=4)
    robot.kit.motor1.throttle, robot.kit.motor2.throttle = 0.5, -0.5  # spin in place
    clock = RealClock()
    hooked_steps: list[float] = []
    emulator = robot.make_lidar(clock, after_step=lambda: hooked_steps.append(float(robot.time_s or 0.0)))
    assert emulator.self_paced and emulator.model is MODELS[config.sim.lidar_model]
    ahead_s = lidar_lead_over_physics(robot)

    async def run() -> int:
        sim = asyncio.create_task(robot.run(clock))
        line = SimLidarLine(emulator)
        seen = 0
        try:
            async with RPLidar(line.connect, clock, spin_up_s=0.1) as lidar:
                scans = lidar.scans()
                async with contextlib.aclosing(scans):  # type: ignore[type-var]
                    async for _ in scans:
                        seen += 1
                        if seen == 8:
                            break
        finally:
            sim.cancel()
            await line.close()
        return seen

    assert run_virtual(asyncio.wait_for(run(), 60.0)) == 8
    assert len(ahead_s) > 50  # a send every ~20 ms for ~1.6 s
    assert max(ahead_s) <= 1.0 / config.sim.physics_rate_hz  # within the physics' own sub-step
    assert hooked_steps  # the steps the lidar made ran the world's hook

    config.sim.lidar_model = "s2"
    assert robot.make_lidar(clock).model is MODELS["s2"]  # the configured device, in every world


def test_a_steps_edges_come_in_the_order_they_happened_on_both_wheels_each_with_its_own_time() -> None:
    # lgpio hands the edges of all lines to one thread in the order of their stamps: a reader
    # anywhere in a step's edges finds both wheels counted up to the same moment. A world step
    # late by 80 ms (a loaded machine) used to send the left wheel's 80 ms of edges, then the
    # right's, all stamped with the step's end: a reader in between found the right wheel silent.
    from mazebot.sim.world_process import EdgeRecordingFactory, drive_edges, encoder_pins

    config = Config()
    config.sim.slip_std = 0.0
    factory = EdgeRecordingFactory(encoder_pins(config))
    robot = SimulatedRobot(_open_world(), config, seed=1, pin_factory=factory)
    motors = DifferentialMotors.from_config(config.motors, robot.kit, RealClock(), loop=None)
    try:
        robot.step(10.0)
        motors.set(-0.5, 0.5)  # spin in place: both wheels at the same speed
        robot.step(10.3)  # up to speed
        factory.take_message()
        robot.step(10.38)  # one late step
        edges: list[tuple[float, int]] = []
        drive_edges(factory.take_message(), [0, 1, 2, 3],  # type: ignore[list-item]
                    lambda index, level, time_s: edges.append((time_s, index)))
    finally:
        motors.close()
        robot.close()
    times = [t for t, _ in edges]
    assert len(edges) > 100 and times == sorted(times)
    assert 10.3 < times[0] < 10.31 and 10.37 < times[-1] <= 10.38 + 1e-6  # spread over the step
    share = sum(index < 2 for _, index in edges) / len(edges)  # pins 0, 1 the left wheel's, 2, 3 the right's
    left = 0
    for k, (_, index) in enumerate(edges, start=1):
        left += index < 2
        assert abs(left - share * k) <= 3  # never one wheel ahead of the other (by more than a few edges)
