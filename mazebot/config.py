"""The configuration of one robot: pydantic models of ``config.toml``.

Every tunable lives here, grouped in one section per part of the robot. Unknown keys
are rejected (a typo must not silently fall back to a default), every number carries
its unit in its name, and ``mazebot config defaults`` renders these models (with the
descriptions as comments) into a complete default file.

Algorithms never receive this object: small ``from_config`` builders at the edge pick
the plain values they need.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from mazebot.errors import ConfigError

#: Absolute speed limits of the robot; the configured limits may not exceed them.
ABSOLUTE_MAX_SPEED_MPS = 0.5
ABSOLUTE_MAX_YAW_RATE_RADPS = 1.2

ENV_CONFIG = "MAZEBOT_CONFIG"
#: A robot name: one chunk of a Zenoh key expression, without its wildcards and separators (`*`, `$`, `/`).
ROBOT_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")

BcmPin = Annotated[int, Field(ge=0, le=27)]


class Section(BaseModel):
    """A config section: unknown keys rejected, values validated on assignment.

    ``defer_build``: a model's validator is built on its first use, not at import
    (https://docs.pydantic.dev/latest/api/config/#pydantic.config.ConfigDict.defer_build),
    so a command that needs one section (``mazebot motors stop``) does not pay for all.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, defer_build=True)


class LidarConfig(Section):
    """Slamtec RPLidar on its USB serial adapter (an A1M8 by default; A2, A3, C1, S2 too)."""

    port: str = Field("/dev/ttyUSB0", description="serial device of the lidar's USB adapter")
    baudrate: int = Field(
        115200,
        gt=0,
        description="serial speed: A1, A2M8 115200; A2M12, A3 256000; C1 460800; S2 1000000 (Slamtec rplidar_ros)",
    )
    scan_mode: Literal["auto", "standard", "express", "boost", "sensitivity", "stability", "denseboost"] = Field(
        "standard",
        description="standard: 5-byte samples (A1 ~2000/s); express: legacy capsules (A1 ~4000/s); "
        "auto: the mode the unit calls typical; boost, sensitivity, stability, denseboost: that mode by name",
    )
    motor_control: Literal["dtr", "none"] = Field(
        "dtr",
        description="dtr: the A1 USB adapter drives the motor from DTR (cleared = spinning); "
        "none: the motor is powered some other way",
    )
    spin_up_s: float = Field(
        0.5, gt=0, le=5, description="wait after starting the motor before asking for a scan"
    )
    no_data_timeout_s: float = Field(
        1.0, gt=0, le=30, description="restart the scan when no sample arrives for this long"
    )
    reconnect_backoff_min_s: float = Field(
        0.5, gt=0, description="first wait before reopening a port that vanished"
    )
    reconnect_backoff_max_s: float = Field(
        8.0, gt=0, description="longest wait between reconnect attempts"
    )
    min_range_m: float = Field(
        0.15, ge=0, description="returns closer than this are invalid (A1M8 datasheet: 0.15 m)"
    )
    max_range_m: float = Field(12.0, gt=0, description="returns farther than this are invalid")
    mount_yaw_deg: float = Field(
        0.0, ge=-180, le=180, description="angle of the lidar's 0° mark from the robot's heading"
    )
    mount_x_m: float = Field(0.0, description="lidar centre ahead of the wheel axle centre")
    mount_y_m: float = Field(0.0, description="lidar centre left of the wheel axle centre")

    @model_validator(mode="after")
    def _ranges_ordered(self) -> LidarConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})"
            )
        if self.reconnect_backoff_min_s > self.reconnect_backoff_max_s:
            raise ValueError("reconnect_backoff_min_s must not exceed reconnect_backoff_max_s")
        return self


class EncodersConfig(Section):
    """One quadrature encoder per drive wheel, on BCM GPIO numbers."""

    left_a_pin: BcmPin = Field(17, description="BCM pin of the left encoder's channel A")
    left_b_pin: BcmPin = Field(18, description="BCM pin of the left encoder's channel B")
    right_a_pin: BcmPin = Field(22, description="BCM pin of the right encoder's channel A")
    right_b_pin: BcmPin = Field(23, description="BCM pin of the right encoder's channel B")
    counts_per_rev: int = Field(
        210,
        gt=0,
        description="encoder lines (pulses of channel A) per wheel revolution, after the gearbox "
        "(e.g. a 7-pulse hall encoder on a 30:1 gear motor)",
    )
    decoding: Literal["x1", "x2", "x4"] = Field(
        "x4", description="edges counted per line: x1 (A rising), x2 (A both), x4 (A and B both)"
    )
    pull_up: bool = Field(True, description="enable the Pi's internal pull-ups on A and B")
    left_invert: bool = Field(False, description="count the left wheel backwards")
    right_invert: bool = Field(True, description="count the right wheel backwards (mirrored)")
    odometry_rate_hz: float = Field(
        50.0, ge=10, le=1000, description="rate of dead reckoning from encoder ticks"
    )

    @model_validator(mode="after")
    def _pins_distinct(self) -> EncodersConfig:
        pins = [self.left_a_pin, self.left_b_pin, self.right_a_pin, self.right_b_pin]
        if len(set(pins)) != len(pins):
            raise ValueError(f"encoder pins must be four different GPIOs, got {pins}")
        return self

    @property
    def ticks_per_rev(self) -> int:
        """Counted ticks per wheel revolution for the chosen decoding."""
        return self.counts_per_rev * {"x1": 1, "x2": 2, "x4": 4}[self.decoding]


class MotorsConfig(Section):
    """Two DC gear motors on the Adafruit DC & Stepper Motor HAT, or on an H-bridge board on GPIO pins."""

    backend: Literal["motorkit", "gpio", "fake"] = Field(
        "motorkit",
        description="motorkit: the Adafruit HAT over I2C; gpio: an H-bridge on GPIO pins (L298N, DRV8833, "
        "TB6612, phase/enable boards); fake: no hardware (tests)",
    )
    gpio_driver: Literal["in1_in2", "phase_enable"] = Field(
        "in1_in2",
        description="gpio: in1_in2: two PWM inputs per motor (L298N, DRV8833, TB6612); phase_enable: a direction "
        "pin and a PWM enable pin (DRV8835 in PHASE/ENABLE mode, Cytron MDD10A DIR/PWM)",
    )
    gpio_motor1_pins: list[BcmPin] = Field(
        [5, 6],
        description="gpio: BCM pins of channel 1; in1_in2: IN1, IN2 and, if wired, the enable (ENA, held high); "
        "phase_enable: PHASE, ENABLE",
    )
    gpio_motor2_pins: list[BcmPin] = Field([13, 19], description="gpio: BCM pins of channel 2, as for channel 1")
    i2c_address: int = Field(0x60, ge=0x03, le=0x77, description="I2C address of the HAT")
    pwm_frequency_hz: float = Field(
        1600.0, ge=24, le=2000,
        description="PWM frequency of the HAT's PCA9685 (MotorKit's default is 1600 Hz) or of the gpio pins"
    )
    left_channel: Literal[1, 2, 3, 4] = Field(1, description="HAT motor terminal of the left wheel")
    right_channel: Literal[1, 2, 3, 4] = Field(
        2, description="HAT motor terminal of the right wheel"
    )
    left_invert: bool = Field(False, description="reverse the left motor's polarity in software")
    right_invert: bool = Field(True, description="reverse the right motor's polarity (mirrored)")
    command_ttl_s: float = Field(
        0.3, gt=0, le=2, description="a throttle not refreshed within this time becomes a stop"
    )

    @model_validator(mode="after")
    def _channels_distinct(self) -> MotorsConfig:
        if self.left_channel == self.right_channel:
            raise ValueError(f"left and right motors share channel {self.left_channel}")
        if self.backend == "gpio":
            if {self.left_channel, self.right_channel} != {1, 2}:
                raise ValueError('with backend = "gpio" the channels are 1 and 2 (gpio_motor1_pins, gpio_motor2_pins)')
            counts = (2, 3) if self.gpio_driver == "in1_in2" else (2,)
            named = (("gpio_motor1_pins", self.gpio_motor1_pins), ("gpio_motor2_pins", self.gpio_motor2_pins))
            for name, pins in named:
                if len(pins) not in counts:
                    wanted = "IN1, IN2 and optionally the enable" if self.gpio_driver == "in1_in2" else "PHASE, ENABLE"
                    raise ValueError(f"{name} for {self.gpio_driver} takes {wanted}, got {pins}")
            pins = [*self.gpio_motor1_pins, *self.gpio_motor2_pins]
            if len(set(pins)) != len(pins):
                raise ValueError(f"the motors' GPIO pins must all differ, got {pins}")
        return self


class DriveConfig(Section):
    """Geometry and speed limits of the differential drive."""

    wheel_diameter_m: float = Field(
        0.065, gt=0.01, lt=0.5, description="drive wheel diameter (the mean of both when they differ)"
    )
    wheel_diameter_ratio: float = Field(
        1.0, gt=0.8, lt=1.25,
        description="right wheel diameter over the left one's (UMBmark's E_d; `mazebot calibrate` measures it)",
    )
    track_width_m: float = Field(
        0.15, gt=0.03, lt=1.0, description="distance between the wheels' contact points"
    )
    max_speed_mps: float = Field(
        0.3, gt=0, le=ABSOLUTE_MAX_SPEED_MPS, description="forward speed limit (absolute 0.5)"
    )
    max_accel_mps2: float = Field(0.6, gt=0, le=5, description="forward acceleration limit")
    max_yaw_rate_radps: float = Field(
        1.2, gt=0, le=ABSOLUTE_MAX_YAW_RATE_RADPS, description="turn rate limit (absolute 1.2)"
    )
    max_yaw_accel_radps2: float = Field(3.0, gt=0, le=20, description="turn acceleration limit")
    max_wheel_speed_mps: float = Field(
        0.6, gt=0, le=3, description="wheel surface speed at full throttle (for feed-forward)"
    )


class RobotConfig(Section):
    """The robot's body."""

    footprint_radius_m: float = Field(
        0.09, gt=0.02, lt=0.5, description="radius of a circle that holds the whole robot"
    )
    clearance_m: float = Field(
        0.02, ge=0, lt=0.3, description="extra margin kept from walls beyond the footprint"
    )


class PlannerConfig(Section):
    """Autonomous exploration: the maze graph, the strategy and the local planner (DWA)."""

    rate_hz: float = Field(5.0, ge=1.0, le=20.0, description="planner ticks per second (graph, goal, DWA)")
    strategy: Literal["nearest", "dfs"] = Field(
        "nearest", description="next unknown link: nearest by route cost, or the seed's depth-first search"
    )
    mode: Literal["auto", "maze", "frontier"] = Field(
        "auto", description="maze cells, grid frontiers (any world), or auto: maze when the walls fit a lattice"
    )
    cell_size_m: float = Field(0.3048, gt=0.1, lt=2.0, description="maze cell size (wall pitch), 1 ft")
    cell_size_search: float = Field(
        0.08, ge=0, le=0.2,
        description="the true pitch is measured from the walls within this share of cell_size_m (mazes built "
        "by hand are off by a few %); 0: exactly cell_size_m",
    )
    wall_thickness_m: float = Field(0.012, gt=0, lt=0.1, description="maze wall thickness")
    goal_tolerance_m: float = Field(0.06, gt=0.01, lt=0.3, description="this close to a goal counts as arrived")
    progress_revolutions: int = Field(
        110, ge=5, le=2000,
        description="a goal whose route cost stops dropping for this many map revolutions (SLAM's painted "
        "scans, ~5.5/s) is blacklisted",
    )
    dwell_revolutions: int = Field(
        16, ge=1, le=400, description="a goal still unresolved this many map revolutions after arriving is blacklisted"
    )
    retry_after_m: float = Field(
        0.9, ge=0, le=100, description="a blacklisted goal is tried again once the robot has driven this far"
    )
    max_attempts: int = Field(
        3, ge=1, le=20,
        description="times a goal is tried before it is given up (the last ones when nothing else is left)",
    )
    horizon_s: float = Field(1.2, gt=0.2, le=5.0, description="DWA rollout length")
    stuck_timeout_s: float = Field(
        4.0, gt=0.5, le=30,
        description="no progress along the path for this many seconds of planner ticks run (20 at 5 Hz; "
        "not wall time) starts a recovery",
    )
    max_recoveries: int = Field(3, ge=1, le=20, description="recoveries on one path before its goal is given up")
    map_window_m: float = Field(
        0.8, gt=0.2, le=5.0, description="radius of map and wall points around the robot given to the DWA"
    )


class ControlConfig(Section):
    """Wheel speed control and the safety layer in front of the motors."""

    wheel_kp: float = Field(0.5, ge=0, le=10, description="wheel speed PI: throttle per m/s of error")
    wheel_ki: float = Field(4.0, ge=0, le=100, description="wheel speed PI: throttle per m of accumulated error")
    wheel_kd: float = Field(0.0, ge=0, le=10, description="wheel speed D (on the measurement): throttle per m/s²")
    integral_limit: float = Field(0.3, ge=0, le=1, description="largest throttle the integral may contribute")
    motor_deadband: float = Field(
        0.08, ge=0, lt=0.8, description="throttle below which the motors do not turn (feed-forward)"
    )
    max_wheel_accel_mps2: float = Field(1.0, gt=0, le=10, description="ramp of each wheel's speed target")
    actuation_latency_s: float = Field(
        0.05, ge=0, le=0.5, description="time from a throttle write to the wheel reacting"
    )
    command_ttl_ticks: int = Field(
        10, ge=2, le=100,
        description="a planner command seen for this many control ticks (0.5 s at 20 Hz) without a new one is a stop",
    )
    scan_timeout_ticks: int = Field(
        20, ge=4, le=200,
        description="no new lidar revolution for this many control ticks (1 s at 20 Hz): only turning in place",
    )
    stop_margin_m: float = Field(
        0.03, ge=0, le=0.5, description="emergency stop: free distance kept ahead beyond the stopping distance"
    )
    brake_decel_mps2: float = Field(0.6, gt=0, le=10, description="deceleration counted on for stopping distances")
    deadline_s: float = Field(
        0.15, gt=0, le=2, description="a control tick later than this after the previous one stops the wheels"
    )


class DaemonConfig(Section):
    """The ``mazebot run`` process."""

    log_level: Literal["debug", "info", "warning", "error"] = Field(
        "info", description="stderr log level (journald adds timestamps)"
    )
    exit_on_fault: bool = Field(
        False,
        description="exit (code 70) when a task crashes; default: stop motors, keep serving",
    )
    state_dir: str = Field(
        "", description="where runs and the control token are kept; empty: a per-user default"
    )
    control_period_s: float = Field(
        0.05, gt=0.001, le=0.5, description="period of the motor control loop (20 Hz)"
    )
    control_thread: bool = Field(
        True,
        description="on the real clock, tick the motor control loop on a thread of its own, so a due tick "
        "never waits for a revolution's SLAM or a planner tick to yield",
    )
    control_process: bool = Field(
        False,
        description="on the real clock, run the motor control loop in a process of its own (its own interpreter "
        "lock: a due tick never waits for the main process), where the motor driver can be opened there; "
        "else the thread",
    )
    auto_resume: bool = Field(
        False, description="resume a run by itself when the fault that stopped it clears; default: press start"
    )
    lidar_silence_s: float = Field(
        0.4, gt=0.1, le=10, description="no lidar revolution this long is a fault: the wheels stop"
    )
    startup_grace_s: float = Field(
        5.0, ge=0, le=60, description="time the lidar gets at start-up before its silence is a fault"
    )


class WebConfig(Section):
    """The web page and websocket served to the phone."""

    host: str = Field("0.0.0.0", description="interface to bind; 127.0.0.1 keeps it local")
    port: int = Field(8080, ge=1, le=65535, description="TCP port of the web page")
    bind_wait_s: float = Field(
        60.0, ge=0, le=600,
        description="how long to wait for host's address to come up (Wi-Fi joining after boot); 0: fail at once",
    )
    broadcast_hz: float = Field(5.0, gt=0, le=30, description="websocket packets per second at most (only on change)")
    resync_every: int = Field(50, ge=2, le=10000, description="every this many packets is a full map (periodic resync)")
    view_open: bool = Field(True, description="anyone on the network may watch; false: watching needs the token too")
    control_token: str = Field(
        "", description="PIN/token for start and stop; empty: generated on first start, kept in the state dir"
    )
    allowed_origins: list[str] = Field(
        default_factory=list,
        description="extra browser origins allowed besides the page's own, e.g. \"http://robot.local:8080\"",
    )
    @field_validator("allowed_origins")
    @classmethod
    def _origins_are_origins(cls, origins: list[str]) -> list[str]:
        """A browser's ``Origin`` is ``scheme://host[:port]``, nothing more: anything else never matches."""
        for origin in origins:
            if origin == "*":
                continue
            parts = urlsplit(origin)
            try:
                parts.port  # noqa: B018 - raises on a port that is not a number
            except ValueError:
                parts = parts._replace(scheme="")
            if parts.scheme not in ("http", "https") or not parts.hostname or parts.path or parts.query:
                raise ValueError(f"{origin!r} is not an origin like \"http://robot.local:8080\" "
                                 "(http or https, a host, an optional port, no path)")
        return origins

    send_queue_packets: int = Field(
        8, ge=2, le=1000, description="packets queued per viewer; a viewer further behind gets a full map instead"
    )
    max_message_bytes: int = Field(4096, ge=256, le=1 << 20, description="largest message a viewer may send")
    message_rate_per_s: float = Field(
        20.0, gt=0, le=10000, description="messages a second one websocket client may send; excess is dropped"
    )
    message_burst: int = Field(
        40, ge=1, le=100000, description="messages a client may send at once; another burst over the rate closes it"
    )
    connect_rate_per_s: float = Field(
        5.0, gt=0, le=10000, description="new websocket connections a second from one address; excess: HTTP 429"
    )
    connect_burst: int = Field(20, ge=1, le=100000, description="connections one address may open at once")
    heartbeat_s: float = Field(10.0, gt=0.5, le=300, description="websocket ping and heartbeat period; dead ones close")
    trail_points: int = Field(1000, ge=0, le=100000, description="trajectory points a new viewer gets (the tail)")


class SimConfig(Section):
    """The simulated robot and world used by ``mazebot run --sim`` and ``mazebot bench``.

    The simulated robot is the one the other sections describe (wheel size, track, pins,
    channels, inversion), plus the imperfections below that a real robot has.
    """

    world: Literal["maze", "room"] = Field(
        "maze", description="maze: a maze file or a generated maze; room: the room with cylinders below"
    )
    maze: str = Field("", description="maze file (micromouse text); empty: generate one")
    maze_kind: Literal["perfect", "braided", "rooms"] = Field(
        "braided", description="kind of generated maze: perfect (a tree), braided (loops), rooms (open 3x3 areas)"
    )
    maze_width: int = Field(6, ge=2, le=32, description="generated maze width in cells")
    maze_height: int = Field(6, ge=2, le=32, description="generated maze height in cells")
    seed: int = Field(1, ge=0, description="seed of the maze generator and of every noise source")
    cell_size_m: float = Field(0.3048, gt=0.1, le=2.0, description="maze cell size (1 ft)")
    wall_thickness_m: float = Field(0.012, gt=0.001, le=0.1, description="maze wall thickness")
    maze_build: Literal["exact", "hand"] = Field(
        "exact",
        description="exact: walls on a perfect lattice of cell_size_m; hand: built from boards by hand "
        "(the hand_* keys below: pitch, offsets, turns, gaps, thickness, angle, clutter)",
    )
    hand_pitch_error_max: float = Field(
        0.03, ge=0, lt=0.2, description="hand: the true pitch is cell_size_m times 1 + uniform(-this, this)"
    )
    hand_line_jitter_m: float = Field(
        0.005, ge=0, lt=0.05, description="hand: each row or column of posts off its place by uniform(-this, this)"
    )
    hand_wall_offset_std_m: float = Field(
        0.004, ge=0, lt=0.03, description="hand: each wall board off the line between its posts (std, across)"
    )
    hand_wall_turn_std_deg: float = Field(0.7, ge=0, lt=5, description="hand: each wall board turned (std)")
    hand_post_gap_min_m: float = Field(0.002, ge=0, lt=0.05, description="hand: gap between a board and a post ...")
    hand_post_gap_max_m: float = Field(0.006, ge=0, lt=0.05, description="... up to this (uniform, per end)")
    hand_wall_thickness_min_m: float = Field(
        0.006, gt=0.001, le=0.05, description="hand: board thickness, uniform per board from this ..."
    )
    hand_wall_thickness_max_m: float = Field(0.020, gt=0.001, le=0.05, description="... to this")
    hand_post_size_m: float = Field(0.012, gt=0.001, le=0.05, description="hand: side of the square posts")
    hand_maze_angle_deg: float = Field(
        -1.0, ge=-1, lt=360, description="hand: the whole maze turned by this in the world (-1: random, seeded)"
    )
    hand_start_heading_std_deg: float = Field(
        3.0, ge=0, le=45, description="hand: the robot put down this far (std) off the start cell's axis"
    )
    hand_clutter: int = Field(
        3, ge=0, le=20,
        description="hand: table legs (small discs) standing in cell corners; a floor cable is below the "
        "lidar's plane and not modelled",
    )
    hand_clutter_diameter_m: float = Field(0.02, gt=0.002, le=0.05, description="hand: a table leg's diameter")
    room_width_m: float = Field(2.0, gt=0.5, le=20, description="room world: inside width")
    room_height_m: float = Field(1.2, gt=0.5, le=20, description="room world: inside depth")
    room_cylinders: int = Field(4, ge=0, le=50, description="room world: cylindrical posts placed at random")
    room_cylinder_diameter_m: float = Field(0.08, gt=0.01, le=1, description="room world: post diameter")
    physics_rate_hz: float = Field(400.0, ge=200, le=5000, description="integration rate of the robot physics")
    step_period_s: float = Field(
        0.01, gt=0, le=0.05, description="period of the simulator task; physics sub-steps at physics_rate_hz"
    )
    lidar_paced_by_robot: bool = Field(
        False, description="the simulator task also sends the lidar's samples (one timer, never ahead of the physics)"
    )
    motor_time_constant_s: float = Field(0.08, gt=0, le=2, description="first-order lag of a driven wheel")
    brake_time_constant_s: float = Field(0.04, gt=0, le=2, description="lag of a wheel braked at throttle 0")
    deadband: float = Field(0.08, ge=0, lt=1, description="throttle below which a motor does not turn")
    gain_left: float = Field(1.0, gt=0.5, lt=1.5, description="left motor speed gain (mismatch)")
    gain_right: float = Field(0.97, gt=0.5, lt=1.5, description="right motor speed gain (mismatch)")
    battery_sag: float = Field(0.05, ge=0, lt=0.5, description="speed loss at full throttle on both motors")
    wheel_diameter_left_scale: float = Field(
        1.0, gt=0.9, lt=1.1, description="true left wheel diameter over the configured one"
    )
    wheel_diameter_right_scale: float = Field(
        1.004, gt=0.9, lt=1.1, description="true right wheel diameter over the configured one"
    )
    slip_std: float = Field(0.01, ge=0, lt=0.5, description="random wheel slip (fraction, per physics step)")
    turn_slip: float = Field(
        0.0, ge=0, lt=0.5, description="share of the wheels' turning the body loses (tyres scrub in turns)"
    )
    backlash_deg: float = Field(
        0.0, ge=0, le=20, description="gearbox play: the motor (and its encoder) turns this far before the wheel does"
    )
    robot_build: Literal["exact", "cheap"] = Field(
        "exact",
        description="cheap: a robot of cheap parts, for keys not set in this file (20-line encoders, wheels 3 % "
        "apart, 5 % slip in turns, 3 deg of gearbox backlash; see CHEAP_ROBOT in config.py)",
    )
    # the true robot where it differs from what the other sections say (what `mazebot calibrate` finds)
    track_width_scale: float = Field(
        1.0, gt=0.8, lt=1.25, description="true track width over the configured one"
    )
    lidar_mount_yaw_error_deg: float = Field(
        0.0, ge=-45, le=45, description="true lidar mounting yaw minus the configured one"
    )
    motor_channels_swapped: bool = Field(
        False, description="the left wheel's motor is on the configured right channel, and the other way round"
    )
    left_motor_reversed: bool = Field(False, description="the left motor is wired the other way than [motors] says")
    right_motor_reversed: bool = Field(False, description="the right motor is wired the other way than [motors] says")
    encoder_pins_swapped: bool = Field(
        False, description="the left wheel's encoder is on the configured right pins, and the other way round"
    )
    left_encoder_reversed: bool = Field(
        False, description="the left encoder counts the other way than [encoders] says"
    )
    right_encoder_reversed: bool = Field(
        False, description="the right encoder counts the other way than [encoders] says"
    )
    lidar_model: Literal["a1", "a2m8", "a2m12", "a3", "c1", "s2"] = Field(
        "a1", description="which RPLidar the emulator is: its rotation rate, scan modes, sample rates, serial speed"
    )
    lidar_rev_jitter: float = Field(0.03, ge=0, lt=0.5, description="relative jitter of the rotation rate")
    lidar_range_noise: float = Field(0.01, ge=0, lt=0.2, description="range noise std as a fraction of range")
    lidar_dropout: float = Field(0.02, ge=0, lt=1, description="probability that a sample has no return")

    @model_validator(mode="after")
    def _hand_ranges(self) -> SimConfig:
        if self.hand_post_gap_min_m > self.hand_post_gap_max_m:
            raise ValueError("hand_post_gap_min_m must not exceed hand_post_gap_max_m")
        if self.hand_wall_thickness_min_m > self.hand_wall_thickness_max_m:
            raise ValueError("hand_wall_thickness_min_m must not exceed hand_wall_thickness_max_m")
        return self


class SlamConfig(Section):
    """SLAM: scan preparation, odometry filter, ICP, keyframes, loop closure, occupancy grid."""

    scan_queue_size: int = Field(2, ge=1, le=32, description="revolutions waiting for SLAM; the oldest is dropped")
    odometry_history_s: float = Field(
        3.0, ge=0.5, le=60, description="odometry kept for de-skew and the filter (time-stamped poses)"
    )
    # scan preparation
    max_range_m: float = Field(
        8.0, gt=0.2, le=40, description="farther returns only clear space (never matched, never a wall)"
    )
    median_window: int = Field(3, ge=1, le=15, description="samples in the running median of impulse rejection (odd)")
    impulse_abs_m: float = Field(
        0.05, ge=0, description="a sample this far plus impulse_rel from its median is a spike"
    )
    impulse_rel: float = Field(0.05, ge=0, description="relative part of the spike threshold")
    voxel_m: float = Field(0.025, gt=0.001, le=0.5, description="point spacing of a scan for matching")
    # odometry filter (EKF)
    odom_var_xy_m2_per_m: float = Field(
        4e-4, gt=0, description="odometry position variance growth per metre travelled (each axis)"
    )
    odom_var_theta_rad2_per_m: float = Field(1e-4, gt=0, description="odometry heading variance per metre travelled")
    odom_var_theta_rad2_per_rad: float = Field(
        2.5e-3, gt=0, description="odometry heading variance per radian turned"
    )
    odom_calibration: bool = Field(
        True, description="learn the odometry's heading bias (unequal wheels, track width) from scan matches"
    )
    odom_calibration_memory_scans: float = Field(
        1000.0, ge=10, description="scans the heading calibration remembers (exponential forgetting)"
    )
    lidar_time_offset_s: float = Field(
        0.0, ge=-0.05, le=0.1, description="how late the lidar's time stamps are against the odometry's (start value)"
    )
    estimate_time_offset: bool = Field(
        True, description="learn that offset online from how scan matches disagree with odometry when turns start"
    )
    filter_gate_chi2: float = Field(
        16.27, gt=0, description="refuse a scan match this unlikely under the prediction (chi2, 3 dof)"
    )
    # scan matching (ICP)
    icp_max_iterations: int = Field(150, ge=1, le=1000, description="ICP iterations at most")
    icp_converged_m: float = Field(0.01, gt=0, description="ICP converged: last step below this ...")
    icp_converged_rad: float = Field(0.01, gt=0, description="... and below this rotation")
    icp_stop_m: float = Field(5e-4, gt=0, description="ICP refines until its step is below this ...")
    icp_stop_rad: float = Field(5e-4, gt=0, description="... and this rotation")
    icp_max_correspondence_m: float = Field(0.3, gt=0, description="first distance gate of ICP correspondences")
    icp_min_correspondence_m: float = Field(0.05, gt=0, description="the adaptive gate never shrinks below this")
    icp_degeneracy_ratio: float = Field(
        0.02, ge=0, lt=1, description="eigenvalue ratio below which a direction counts as unobservable"
    )
    icp_min_fitness: float = Field(0.5, ge=0, le=1, description="share of points matched for the filter to use a match")
    icp_max_rmse_m: float = Field(0.03, gt=0, description="... and at most this point-to-line residual")
    icp_retry_headings_rad: list[float] = Field(
        [0.05, -0.05, 0.1, -0.1], description="when a match fails, retry ICP from the prediction turned by these"
    )
    icp_information_scale: float = Field(
        0.5, gt=0, le=1, description="scale of ICP's information matrix (ICP is optimistic about itself)"
    )
    icp_range_noise_ratio: float = Field(
        0.0,
        ge=0,
        lt=0.3,
        description="weight ICP residuals by the lidar's range noise, std / range (A1: 0.01; 0: all points alike)",
    )
    icp_noise_floor_m: float = Field(
        0.002, gt=0, description="... plus this std that does not grow with range (submap pose errors)"
    )
    normal_neighbours: int = Field(10, ge=3, le=50, description="neighbours for surface normals")
    normal_radius_m: float = Field(0.1, gt=0, description="neighbours farther than this do not count for a normal")
    # keyframes, local submap, pose graph
    keyframe_distance_m: float = Field(0.10, gt=0, description="a scan becomes a keyframe after this much travel ...")
    keyframe_angle_rad: float = Field(0.2, gt=0, description="... or this much turn (11°: eight in a 90° turn)")
    submap_keyframes: int = Field(20, ge=1, le=500, description="recent keyframes in the local submap ICP matches")
    submap_radius_m: float = Field(
        0.5, ge=0, description="older keyframes this close to the robot join the local submap (0: only recent ones)"
    )
    submap_near_keyframes: int = Field(20, ge=0, le=500, description="at most this many older keyframes, nearest first")
    submap_voxel_m: float = Field(0.01, gt=0.001, le=0.5, description="point spacing of the local submap")
    submap_update_m: float = Field(
        0.05, ge=0, description="rebuild the local submap at a keyframe this far from the last rebuild ..."
    )
    submap_update_keyframes: int = Field(4, ge=1, description="... or after this many keyframes")
    optimize_iterations: int = Field(30, ge=1, le=500, description="Levenberg-Marquardt iterations per optimization")
    wall_prior: bool = Field(
        True, description="walls meet at right angles (a maze): each keyframe's walls give a weak heading prior"
    )
    wall_prior_std_rad: float = Field(0.01, gt=0, description="trust in one keyframe's wall direction")
    wall_min_strength: float = Field(
        0.6, ge=0, le=1, description="use a keyframe only if its wall normals are this aligned to a right-angle grid"
    )
    anchor_revolutions: int = Field(
        20, ge=1, le=100, description="revolutions at rest keyframe 0, the map's anchor, measures its walls over"
    )
    wall_anchor_std_rad: float = Field(
        0.001, gt=0, description="trust in the anchor's wall direction (it fixes the wall grid of the whole map)"
    )
    wall_lattice: bool = Field(
        True,
        description="walls lie on a square lattice of the planner's cell size: each keyframe's wall faces "
        "give a weak position prior (needs wall_prior)",
    )
    wall_lattice_std_m: float = Field(0.005, gt=0, description="trust in one keyframe's wall faces on the lattice")
    wall_lattice_gate_m: float = Field(
        0.04, gt=0, description="a face farther than this from its lattice line is not used for the prior"
    )
    optimize_every_keyframes: int = Field(
        20, ge=1, description="optimize the pose graph this often even without a loop closure (wall priors)"
    )
    # loop closure
    loop_search_radius_m: float = Field(0.25, gt=0, description="look for loop closures at least this close ...")
    loop_max_search_radius_m: float = Field(1.0, gt=0, description="... and never farther than this")
    loop_sigma_scale: float = Field(3.0, ge=0, description="search radius grows by this many std of the drift")
    loop_min_keyframe_gap: int = Field(40, ge=2, description="a candidate is at least this many keyframes old")
    loop_submap_half_width: int = Field(6, ge=0, le=100, description="candidate submap: keyframes i-k .. i+k")
    loop_attempt_every: int = Field(3, ge=1, description="look for loop closures every this many keyframes")
    loop_min_fitness: float = Field(0.8, ge=0, le=1, description="accept: at least this share of points matched")
    loop_max_rmse_m: float = Field(0.012, gt=0, description="accept: point-to-line RMS at most this")
    loop_min_correspondences: int = Field(40, ge=3, description="accept: at least this many matched points")
    loop_accept_degenerate: bool = Field(False, description="accept matches that leave a direction unconstrained")
    loop_gate_chi2: float = Field(11.34, gt=0, description="accept: correction consistent with odometry (chi2, 3 dof)")
    loop_max_correction_m: float = Field(0.10, gt=0, description="accept: the correction moves at most this far ...")
    loop_max_correction_rad: float = Field(0.15, gt=0, description="... and turns at most this much")
    loop_ambiguity_shift_m: float = Field(
        0.3048, ge=0, description="retry ICP this far off (one cell); another good fit there rejects (0: off)"
    )
    loop_ambiguity_fitness_ratio: float = Field(
        0.85, gt=0, le=1, description="that other fit counts if its inlier ratio is this share of the match's ..."
    )
    loop_ambiguity_rmse_ratio: float = Field(4.0, ge=1, description="... and its residual at most this many times")
    loop_max_range_m: float = Field(
        2.0, ge=0, description="verify a loop closure with the points this close to the lidar (0: all)"
    )
    loop_information_scale: float = Field(0.1, gt=0, le=1, description="scale of a loop closure's ICP information")
    loop_dcs_phi: float = Field(
        11.34, ge=0, description="dynamic covariance scaling: a closure whose chi2 exceeds this loses weight (0: off)"
    )
    # correlative scan matching (Olson, ICRA 2009) before ICP where the prediction is uncertain
    correlative: bool = Field(
        True, description="search a window of poses before ICP where its match failed, or after re-localization"
    )
    corr_resolution_m: float = Field(0.03, gt=0.001, le=1, description="cell of the correlative likelihood table")
    corr_sigma_m: float = Field(0.04, gt=0, le=1, description="smoothing of that table (std of a point's position)")
    corr_window_m: float = Field(
        0.12, ge=0, le=5, description="sequential search: half-width in x and y (under half a maze cell) ..."
    )
    corr_window_rad: float = Field(0.35, ge=0, le=3.2, description="... and in heading")
    corr_levels: int = Field(2, ge=0, le=8, description="branch-and-bound levels of the sequential search")
    corr_max_range_m: float = Field(4.0, gt=0, description="the search uses scan points this close to the lidar ...")
    corr_max_points: int = Field(200, ge=10, description="... at most this many of them")
    corr_min_score: float = Field(0.35, ge=0, le=1, description="a search scoring less found nothing (0..1)")
    corr_uncertain_std_m: float = Field(
        0.05, gt=0, description="search also when the prediction's position std exceeds this (m) ..."
    )
    corr_uncertain_std_rad: float = Field(0.035, gt=0, description="... or its heading std this (rad)")
    corr_window_sigmas: float = Field(
        3.0, gt=0, description="that search's half-widths: this many prediction stds (at most corr_window_*)"
    )
    corr_override_score: float = Field(
        0.05, ge=0, le=1, description="its match replaces an acceptable ICP match scoring this much less (0..1)"
    )
    loop_corr_window_m: float = Field(
        0.1, ge=0, le=10, description="loop closure: branch-and-bound window about the prior, x and y (0: ICP only) ..."
    )
    loop_corr_window_rad: float = Field(0.15, ge=0, le=3.2, description="... and heading")
    loop_corr_levels: int = Field(3, ge=0, le=8, description="branch-and-bound levels of the loop-closure search")
    rebuild_threshold_m: float = Field(
        0.01, ge=0, description="rebuild the map when optimization moved a keyframe farther than this ..."
    )
    rebuild_threshold_rad: float = Field(0.005, ge=0, description="... or turned one more than this")
    loop_closure_executor: Literal["process", "thread"] = Field(
        "process",
        description="run loop-closure jobs in a worker process (a core of its own) or a thread of the daemon",
    )
    # occupancy grid
    grid_resolution_m: float = Field(0.02, gt=0.001, le=1, description="occupancy grid cell size")
    grid_l_hit: float = Field(0.85, gt=0, description="log-odds added to a cell a beam ends in")
    grid_l_miss: float = Field(-0.4, lt=0, description="log-odds added to a cell a beam crosses")
    grid_l_min: float = Field(-5.0, lt=0, description="lowest log-odds of a cell")
    grid_l_max: float = Field(5.0, gt=0, description="highest log-odds of a cell")
    grid_occupied_prob: float = Field(
        0.75, ge=0.5, lt=1, description="a cell above this probability is a wall (0.75: two hits, not one stray)"
    )
    grid_free_prob: float = Field(0.25, gt=0, le=0.5, description="a cell below this probability is free")
    map_max_range_m: float = Field(
        1.2, ge=0, description="farther hits clear space but mark no wall (range noise grows with range; 0: no limit)"
    )
    map_smooth_endpoints: bool = Field(
        True, description="move each hit along its beam onto the line through its neighbours before mapping it"
    )
    range_noise_rel: float = Field(
        0.01, ge=0, lt=0.3, description="the lidar's range noise, std as a fraction of the range (A1: about 1 %)"
    )
    grid_max_free_range_m: float = Field(4.0, gt=0, description="no-return beams clear space this far")
    map_hit_depth_m: float = Field(
        0.006,
        ge=0,
        le=0.05,
        description="a hit marks the cell this far behind the wall's face (under the wall thickness)",
    )

    @model_validator(mode="after")
    def _consistent(self) -> SlamConfig:
        if self.median_window % 2 == 0:
            raise ValueError(f"median_window must be odd, got {self.median_window}")
        if self.icp_min_correspondence_m > self.icp_max_correspondence_m:
            raise ValueError("icp_min_correspondence_m must not exceed icp_max_correspondence_m")
        if self.loop_search_radius_m > self.loop_max_search_radius_m:
            raise ValueError("loop_search_radius_m must not exceed loop_max_search_radius_m")
        return self


class RecordConfig(Section):
    """Recording every sensor stream, command, pose and fault to MCAP (``mazebot run --record``)."""

    enabled: bool = Field(False, description="record every run (as if --record were given)")
    path: str = Field("", description="recording file; empty: recording.mcap in the run's folder")
    max_file_mb: float = Field(512.0, gt=0.1, le=1e6, description="at this size a file is closed and a new one begun")
    keep_files: int = Field(
        4, ge=1, le=1000, description="rotated files kept (FILE.mcap, FILE.001.mcap, ...); the oldest is deleted"
    )
    queue_messages: int = Field(
        2000, ge=10, le=1000000, description="messages waiting for the writer thread; more are dropped and counted"
    )
    pose_hz: float = Field(10.0, gt=0, le=100, description="pose estimates recorded per second")
    map_period_s: float = Field(2.0, gt=0.05, le=600, description="the map (foxglove.Grid) is recorded this often")
    compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="MCAP chunk compression")


class FoxgloveConfig(Section):
    """Foxglove live: the running robot on the Foxglove WebSocket protocol (pip install 'mazebot[foxglove]')."""

    enabled: bool = Field(False, description="serve the live run to Foxglove (app or web) on its own port")
    host: str = Field("", description="interface to bind; empty: the web page's [web] host")
    port: int = Field(8765, ge=1, le=65535, description="TCP port of the Foxglove WebSocket server (the SDK's default)")
    pose_hz: float = Field(10.0, gt=0, le=50, description="pose, odometry and transforms sent per second at most")
    map_period_s: float = Field(
        1.0, gt=0.05, le=600, description="the map (foxglove.Grid) is sent this often when a client watches it"
    )


class PersistConfig(Section):
    """Saving the map, pose graph and keyframes of each run under the state directory."""

    enabled: bool = Field(True, description="save each `mazebot run` under STATE_DIR/runs/<timestamp>/")
    save_period_s: float = Field(10.0, gt=0.5, le=3600, description="save this often while running (and at the end)")


class ZenohConfig(Section):
    """A fleet over Zenoh: state under ``mazebot/<robot_name>/...``, start/stop with the PIN (docs/fleet.md).

    Needs the extra (``pip install 'mazebot[zenoh]'``); ``mazebot watch`` on a laptop shows every
    robot it finds.
    """

    enabled: bool = Field(False, description="publish on Zenoh (needs the zenoh extra: pip install 'mazebot[zenoh]')")
    robot_name: str = Field(
        "", description="this robot's name in the key expressions (letters, digits, - and _); empty: the host name"
    )
    mode: Literal["peer", "client"] = Field(
        "peer", description="peer: meet the others directly (local network); client: only through a router (zenohd)"
    )
    connect: list[str] = Field(
        default_factory=list,
        description="endpoints to connect to, e.g. [\"tcp/192.168.1.10:7447\"] (a zenohd router on another network)",
    )
    listen: list[str] = Field(
        default_factory=list, description="endpoints to listen on, e.g. [\"tcp/0.0.0.0:7447\"]; empty: Zenoh's default"
    )
    multicast_scouting: bool = Field(True, description="find peers and routers on the local network by UDP multicast")
    pose_hz: float = Field(10.0, gt=0, le=50, description="pose estimates (with covariance) published per second")
    scan_every: int = Field(1, ge=1, le=100, description="publish every Nth lidar revolution")
    queue_messages: int = Field(
        256, ge=8, le=100000, description="messages waiting for the publisher thread; more are dropped and counted"
    )
    control_rate_per_s: float = Field(
        2.0, gt=0, le=100, description="start/stop requests taken per second over Zenoh (all of them together)"
    )
    control_burst: int = Field(10, ge=1, le=1000, description="... in bursts of at most this many")

    @field_validator("robot_name")
    @classmethod
    def _name_is_one_chunk(cls, name: str) -> str:
        if name and not ROBOT_NAME.fullmatch(name):
            raise ValueError(f"{name!r} must be letters, digits, '-' and '_' only (it is one key expression chunk)")
        return name


#: ``[sim] robot_build = "cheap"``: a robot of cheap parts. A 20-slot encoder disc on each wheel
#: shaft (the kits' optical interrupters); wheels 3 % apart in diameter (moulded tyres); tyres
#: that scrub 5 % of the turn away in place; and the few degrees of play of a plastic gearbox
#: between the motor and the wheel.
CHEAP_ROBOT: dict[tuple[str, str], object] = {
    ("encoders", "counts_per_rev"): 20,
    ("sim", "wheel_diameter_left_scale"): 0.985,
    ("sim", "wheel_diameter_right_scale"): 1.015,
    ("sim", "turn_slip"): 0.05,
    ("sim", "backlash_deg"): 3.0,
}


class Config(BaseModel):
    """The whole configuration file: one section per part of the robot."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, defer_build=True)

    lidar: LidarConfig = Field(default_factory=LidarConfig)
    encoders: EncodersConfig = Field(default_factory=EncodersConfig)
    motors: MotorsConfig = Field(default_factory=MotorsConfig)
    drive: DriveConfig = Field(default_factory=DriveConfig)
    robot: RobotConfig = Field(default_factory=RobotConfig)
    daemon: DaemonConfig = Field(default_factory=DaemonConfig)
    web: WebConfig = Field(default_factory=WebConfig)
    sim: SimConfig = Field(default_factory=SimConfig)
    slam: SlamConfig = Field(default_factory=SlamConfig)
    planner: PlannerConfig = Field(default_factory=PlannerConfig)
    control: ControlConfig = Field(default_factory=ControlConfig)
    record: RecordConfig = Field(default_factory=RecordConfig)
    foxglove: FoxgloveConfig = Field(default_factory=FoxgloveConfig)
    persist: PersistConfig = Field(default_factory=PersistConfig)
    zenoh: ZenohConfig = Field(default_factory=ZenohConfig)

    @property
    def wheel_circumference_m(self) -> float:
        return math.pi * self.drive.wheel_diameter_m

    @model_validator(mode="after")
    def _robot_build_preset(self) -> Config:
        """``[sim] robot_build = "cheap"``: the :data:`CHEAP_ROBOT` values for every key the file did not set.

        The encoders belong to the robot, not only to the simulator: the daemon must count
        the cheap robot's 20 lines right, so the preset fills ``[encoders]`` too.
        """
        if self.sim.robot_build != "cheap":
            return self
        for (section_name, key), value in CHEAP_ROBOT.items():
            section = getattr(self, section_name)
            if key not in section.model_fields_set:
                section.__dict__[key] = value  # no re-validation: the values are in range by construction
        return self

    @model_validator(mode="after")
    def _motor_pins_free(self) -> Config:
        if self.motors.backend != "gpio":
            return self
        e = self.encoders
        shared = {*self.motors.gpio_motor1_pins, *self.motors.gpio_motor2_pins} & {
            e.left_a_pin, e.left_b_pin, e.right_a_pin, e.right_b_pin}
        if shared:
            raise ValueError(f"motors.gpio_motor*_pins and the [encoders] pins share GPIO {sorted(shared)}")
        return self


#: The system-wide config file, the one the systemd unit names (``systemd/mazebot.service``).
SYSTEM_CONFIG = Path("/etc/mazebot/config.toml")


def config_search_path() -> list[Path]:
    """Where a config file is looked for when no ``--config`` is given, first match wins:
    ``$MAZEBOT_CONFIG``, ``./config.toml``, ``$XDG_CONFIG_HOME/mazebot/config.toml``
    (``~/.config`` when unset, per the XDG Base Directory Specification), ``/etc/mazebot/config.toml``."""
    env = os.environ.get(ENV_CONFIG)
    if env:
        return [Path(env)]  # named explicitly: must exist, no falling through to another file
    xdg = os.environ.get("XDG_CONFIG_HOME") or os.path.join(os.path.expanduser("~"), ".config")
    return [Path("config.toml"), Path(xdg) / "mazebot" / "config.toml", SYSTEM_CONFIG]


def default_config_path() -> Path | None:
    """The config file used without ``--config`` (:func:`config_search_path`), or None: the defaults."""
    env = os.environ.get(ENV_CONFIG)
    if env:
        return Path(env)
    return next((p for p in config_search_path() if p.is_file()), None)


def _describe_error(err: Mapping[str, Any]) -> str:
    path = ".".join(str(p) for p in err["loc"]) or "(top level)"
    kind = err["type"]
    value = err.get("input")
    if kind == "extra_forbidden":
        return f"{path}: unknown key (value {value!r}); check the spelling against `mazebot config defaults`"
    if kind == "missing":
        return f"{path}: required key is missing"
    msg = err["msg"]
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    return f"{path}: {value!r} is not allowed: {msg}"


def _problems(exc: ValidationError, source: str, prefix: str = "") -> ConfigError:
    problems = [f"{source}: {prefix}{_describe_error(e)}" for e in exc.errors()]
    more = len(problems) - 1
    first = problems[0] + (f" (and {more} more: `mazebot config check` lists them)" if more else "")
    return ConfigError(first, problems)


def parse_config(data: dict[str, Any], source: str = "<config>") -> Config:
    """Validate a parsed TOML document; raise ConfigError with one line per problem."""
    try:
        # strict: TOML has real types, so "8080" or true for a port is a mistake, not a port
        return Config.model_validate(data, strict=True)
    except ValidationError as exc:
        raise _problems(exc, source) from None


def read_config_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The TOML document of a config file, not yet validated; ConfigError naming the file if unreadable."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config file ({exc.strerror or exc})") from None
    try:
        return tomllib.loads(raw.decode("utf-8"))  # decoding here: a UnicodeDecodeError is no OSError
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{p}: not valid TOML: the file is not UTF-8 text") from None


def load_config(path: str | os.PathLike[str] | None = None) -> Config:
    """Load and validate a config file; with no path, the file :func:`default_config_path` finds, or the defaults."""
    if path is None:
        path = default_config_path()
        if path is None:
            return Config()
    return parse_config(read_config_file(path), str(path))


def load_motors_config(path: str | os.PathLike[str] | None = None) -> MotorsConfig:
    """Only the ``[motors]`` section of a config file, validated like :func:`load_config` does.

    For ``mazebot motors stop``, the safety net systemd runs after every exit of the daemon:
    a mistake in any other section must not keep it from zeroing the HAT, and building
    only this section's model keeps the command quick (the models are built on first use,
    ``defer_build``).
    """
    if path is None:
        path = default_config_path()
        if path is None:
            return MotorsConfig()
    data = read_config_file(path)
    section = data.get("motors", {})
    if not isinstance(section, dict):
        raise ConfigError(f"{path}: motors: expected a [motors] table, found {section!r}")
    try:
        return MotorsConfig.model_validate(section, strict=True)
    except ValidationError as exc:
        raise _problems(exc, str(path), "motors.") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return f'"{escaped}"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def render_toml(config: Config | None = None) -> str:
    """The config as a commented TOML file (``mazebot config defaults``)."""
    config = config if config is not None else Config()
    lines = [
        "# mazebot configuration. Every key is optional; these are the defaults.",
        "# Check a file with `mazebot config check PATH`.",
    ]
    for name, field in Config.model_fields.items():
        section = getattr(config, name)
        lines.append("")
        lines.append(f"# {(type(section).__doc__ or '').strip().splitlines()[0]}")
        lines.append(f"[{name}]")
        for key, sub in type(section).model_fields.items():
            if sub.description:
                lines.append(f"# {sub.description}")
            lines.append(f"{key} = {_toml_value(getattr(section, key))}")
        del field
    return "\n".join(lines) + "\n"
