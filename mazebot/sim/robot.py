"""The simulated robot: physics, motor HAT, encoder pins and lidar head in one world.

It stands behind the same hardware boundaries as the real robot (docs/design.md, "Hardware
boundaries"): the daemon's motor driver writes throttles into a fake MotorKit, whose
channels turn the simulated wheels; the wheels' true rotation becomes quadrature edges
on gpiozero mock pins that the real encoder code counts; the lidar head measures the
world from the robot's true pose and the emulator serves it as RPLidar protocol bytes.

The simulated robot is the one ``config.toml`` describes (wheel size, track width,
pins, channels, and the wiring that the inversion flags correct for), plus the
imperfections of ``[sim]``: motor lag and mismatch, unequal wheels, slip, lidar noise.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from gpiozero.pins.mock import MockFactory

from mazebot.clock import Clock
from mazebot.config import Config
from mazebot.io.encoders import WheelEncoders
from mazebot.io.motors import FakeMotorKit
from mazebot.io.rplidar_models import MODELS
from mazebot.sim.encoder_signals import QuadratureSignal
from mazebot.sim.lidar_emulator import RPLidarEmulator
from mazebot.sim.lidar_samples import LidarParams, PoseHistory, SpinningLidar
from mazebot.sim.physics import PhysicsParams, RobotPhysics
from mazebot.sim.sim_pins import BoundedHistoryPin, SimPinFactory
from mazebot.sim.world import World


def physics_params(config: Config) -> PhysicsParams:
    """The simulated robot's physics from the robot's config and its ``[sim]`` section."""
    sim = config.sim
    ratio = config.drive.wheel_diameter_ratio  # the configured wheels: mean diameter and right/left
    return PhysicsParams(
        wheel_diameter_m=config.drive.wheel_diameter_m,
        track_width_m=config.drive.track_width_m * sim.track_width_scale,
        max_wheel_speed_mps=config.drive.max_wheel_speed_mps,
        motor_time_constant_s=sim.motor_time_constant_s,
        brake_time_constant_s=sim.brake_time_constant_s,
        deadband=sim.deadband,
        gain_left=sim.gain_left,
        gain_right=sim.gain_right,
        battery_sag=sim.battery_sag,
        wheel_diameter_left_scale=sim.wheel_diameter_left_scale * 2.0 / (1.0 + ratio),
        wheel_diameter_right_scale=sim.wheel_diameter_right_scale * 2.0 * ratio / (1.0 + ratio),
        slip_std=sim.slip_std,
        backlash_rad=math.radians(sim.backlash_deg),
        turn_slip=sim.turn_slip,
        footprint_radius_m=config.robot.footprint_radius_m,
        rate_hz=sim.physics_rate_hz,
    )


def lidar_params(config: Config) -> LidarParams:
    """The emulated lidar from ``[lidar]`` (range limits, mounting) and ``[sim]`` (model,
    noise). The sample rate is the standard mode's until a scan mode starts."""
    sim, lidar = config.sim, config.lidar
    model = MODELS[sim.lidar_model]
    samples = round(1e6 / model.standard_us / model.rev_per_s)
    return LidarParams(
        rev_per_s=model.rev_per_s,
        rev_jitter=sim.lidar_rev_jitter,
        samples_per_rev=samples,
        min_range_m=lidar.min_range_m,
        max_range_m=lidar.max_range_m,
        range_noise=sim.lidar_range_noise,
        dropout=sim.lidar_dropout,
        mount_x_m=lidar.mount_x_m,
        mount_y_m=lidar.mount_y_m,
        mount_yaw_rad=float(np.deg2rad(lidar.mount_yaw_deg + sim.lidar_mount_yaw_error_deg)),
    )


class SimulatedRobot:
    """One robot in one world. ``step(now_s)`` advances everything to ``now_s``.

    Example::

        robot = SimulatedRobot(world, config, seed=1)
        robot.kit.motor1.throttle = 0.5       # what the motor driver does
        robot.step(0.1)                       # physics, encoder edges, pose history
    """

    def __init__(
        self,
        world: World,
        config: Config,
        seed: int,
        clock: Clock | None = None,
        pin_factory: MockFactory | None = None,
    ) -> None:
        self.world = world
        self.config = config
        rngs = np.random.default_rng(seed).spawn(2)
        self.physics = RobotPhysics(physics_params(config), world, world.start_pose, rngs[0])
        self.kit = FakeMotorKit(clock)
        # bounded edge history: gpiozero's MockPin keeps every edge (a leak over long runs);
        # the world process passes a factory that also records the edges it sends to the daemon
        self.pin_factory = (pin_factory if pin_factory is not None
                            else SimPinFactory(pin_class=BoundedHistoryPin,
                                              time_source=clock.now_s if clock is not None else time.monotonic))
        enc = config.encoders
        left_pins, right_pins = (enc.left_a_pin, enc.left_b_pin), (enc.right_a_pin, enc.right_b_pin)
        if config.sim.encoder_pins_swapped:
            left_pins, right_pins = right_pins, left_pins
        # each wheel's encoder, on the pins it is truly wired to
        self.left_signal = QuadratureSignal(self.pin_factory, *left_pins, enc.counts_per_rev, idle_high=enc.pull_up)
        self.right_signal = QuadratureSignal(self.pin_factory, *right_pins, enc.counts_per_rev, idle_high=enc.pull_up)
        self.poses = PoseHistory()
        self.lidar_line: Any = None  # mazebot.sim.backend.SimLidarLine, set by the backend
        #: the daemon's encoders on this robot's pins, set by the backend: the harness taps them
        #: (``on_read``) whether or not a recording wraps ``Hardware.encoders``
        self.encoders: WheelEncoders | None = None
        self._lidar: Any = None  # an RPLidarEmulator paced by this robot's tick (attach_lidar)
        self._lidar_every = 1  # ... every this many ticks
        self.lidar_head = SpinningLidar(world, lidar_params(config), rngs[1])
        self.time_s: float | None = None
        self.trajectory: list[tuple[float, float, float, float]] = []  # (t, x, y, theta), ground truth

    def _channel_throttle(self, channel: int, inverted_wiring: bool) -> float | None:
        throttle = getattr(self.kit, f"motor{channel}").throttle
        if throttle is None:
            return None
        return -throttle if inverted_wiring else throttle

    def step(self, now_s: float) -> None:
        """Advance the world to ``now_s``: motors → physics → encoder pins → pose history."""
        if self.time_s is None:
            self.time_s = now_s
            self._record(now_s)
            return
        start_s, dt_s = self.time_s, now_s - self.time_s
        if dt_s <= 0:
            return
        self.time_s = now_s
        motors, sim = self.config.motors, self.config.sim
        # The wiring the config's inversion flags correct for: a motor flagged inverted
        # is mounted mirrored, so its wheel turns forward on a negative throttle; [sim]
        # may say the true wiring differs (swapped channels, a motor the other way round).
        left_channel, right_channel = motors.left_channel, motors.right_channel
        if sim.motor_channels_swapped:
            left_channel, right_channel = right_channel, left_channel
        self.physics.set_throttle(
            self._channel_throttle(left_channel, motors.left_invert != sim.left_motor_reversed),
            self._channel_throttle(right_channel, motors.right_invert != sim.right_motor_reversed),
        )
        self.physics.step(dt_s)
        left_rad, right_rad = self.physics.wheel_angle_rad
        enc = self.config.encoders
        left, right = self.left_signal, self.right_signal
        # both wheels' edges in the order they happened, each with its own time, as lgpio hands them
        # over on the robot: sent wheel by wheel with the step's time, a reader in the middle of a
        # step's edges found one wheel a whole step ahead of the other (a step is tens of
        # milliseconds when the world process runs late), and a wheel counting nothing meanwhile
        edges = [(share, 0, step) for share, step in
                 left.edges_to(-left_rad if enc.left_invert != sim.left_encoder_reversed else left_rad)]
        edges += [(share, 1, step) for share, step in
                  right.edges_to(-right_rad if enc.right_invert != sim.right_encoder_reversed else right_rad)]
        edges.sort(key=_share)  # stable: a wheel's own edges keep their order
        for share, side, step in edges:
            (right if side else left).emit(step, start_s + share * dt_s)
        self._record(now_s)

    def step_when_behind(self, now_s: float) -> bool:
        """:meth:`step` to ``now_s`` if the world is more than one physics sub-step behind it.

        What a self-paced lidar emulator calls before it measures. Within a sub-step the pose it
        would hold is the physics' own resolution, and the loop's passes (a microsecond each on the
        virtual clock) leave the world that far behind all the time: stepping there would only
        move the sub-steps' boundaries.
        """
        if self.time_s is None or now_s - self.time_s > 1.0 / self.physics.params.rate_hz:
            self.step(now_s)
            return True
        return False

    def _record(self, now_s: float) -> None:
        x, y, th = self.physics.pose
        self.poses.append(now_s, x, y, th)
        if not self.trajectory or now_s - self.trajectory[-1][0] >= 0.05:
            self.trajectory.append((now_s, x, y, th))

    def make_lidar(self, clock: Clock, after_step: Callable[[], None] | None = None) -> RPLidarEmulator:
        """This robot's RPLidar emulator (``[sim] lidar_model``), measuring only poses its physics has reached.

        Every world that serves the daemon a lidar builds it here (the daemon's backend, the
        world process of the CPU-quota bench, the doctor's parts), so none serves an easier or
        an older device than the others. With ``[sim] lidar_paced_by_robot`` the robot's tick
        has it send (:meth:`attach_lidar`); on its own timer it steps the world to the clock's
        time before it measures (:meth:`step_when_behind`): otherwise the samples of up to a
        tick (longer after a loop stall) are measured from the last pose the physics reached
        while the robot turns on. ``after_step`` is called after such a step, as :meth:`run`
        calls it after its own (the world process sends the step's encoder edges there).
        """
        paced = self.config.sim.lidar_paced_by_robot
        emulator = RPLidarEmulator(self.lidar_head, self.poses, clock, model=MODELS[self.config.sim.lidar_model],
                                   self_paced=not paced)
        if paced:
            self.attach_lidar(emulator)
        else:
            def world_catch_up() -> None:
                if self.step_when_behind(clock.now_s()) and after_step is not None:
                    after_step()

            emulator.world_catch_up = world_catch_up
        return emulator

    def attach_lidar(self, emulator: Any) -> None:
        """Let this robot's tick pace the lidar emulator (one built with ``self_paced=False``).

        Every ``emulator.SEND_PERIOD_S`` (rounded to whole ticks) the tick, right after
        stepping the physics, has the emulator send what its head measured since the last
        send. Two periodic tasks become one, and every sample is measured from poses the
        physics has already reached: on its own timer the emulator ran up to one tick
        ahead of the physics and held the last pose for those samples.
        """
        self._lidar = emulator
        self._lidar_every = max(1, round(emulator.SEND_PERIOD_S / self.config.sim.step_period_s))

    def catch_up(self, now_s: float) -> None:
        """The world as it is at ``now_s``, whenever the daemon looks at it or acts on it.

        A real world does not wait for the simulator's next tick: encoders count and the
        lidar streams all the time, and a throttle acts from the moment it is written.
        The backend calls this before each encoder reading, lidar read and throttle write,
        so what the daemon sees is as fresh as on the robot even when its loop is late
        (on a slower computer the reader comes tens of milliseconds after the tick).
        """
        self.step(now_s)
        if self._lidar is not None:
            self._lidar.pump()

    async def run(self, clock: Clock, after_step: Callable[[], None] | None = None) -> None:
        """The simulator task: step the world every ``[sim] step_period_s`` (and pace the lidar).

        ``after_step`` is called after every step (the world process sends the step's encoder
        edges to the daemon there: :mod:`mazebot.sim.world_process`).
        """
        period_s = self.config.sim.step_period_s
        tick = 0
        while True:
            self.step(clock.now_s())
            tick += 1
            if self._lidar is not None and tick % self._lidar_every == 0:
                self._lidar.pump()
            if after_step is not None:
                after_step()
            await clock.sleep(period_s)

    def close(self) -> None:
        self.pin_factory.close()


def _share(edge: tuple[float, int, int]) -> float:
    return edge[0]
