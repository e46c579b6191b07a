"""The configuration of one robot: pydantic models of ``config.toml``.

Every tunable lives here, grouped in one section per part of the robot. Unknown keys
are rejected (a typo must not silently fall back to a default), every number carries
its unit in its name, and ``mazebot config defaults`` renders these models (with the
descriptions as comments) into a complete default file.

Algorithms never receive this object: a section is the parameter object of the part it
names (the SLAM's nested ``[slam.*]`` sections, :mod:`mazebot.slam_config`; the sections
:class:`mazebot.planner.pilot.PilotParams` and :class:`mazebot.tasks.control_task.MotorControl`
take), so each default is written once, here.

Why one module of ~750 lines: it is the schema of one file, ``config.toml``, in the file's
order, with its one loader (search path, old keys migrated, errors naming the key) and its
renderer (``mazebot config defaults``); a section read alone is a class of a few dozen lines
and the file is read section by section. Apart are the two sections that are worlds of their
own, ``[slam]`` (:mod:`mazebot.slam_config`, nested parameter objects) and ``[sim]``
(:mod:`mazebot.sim_config`, the harness's knobs), and what ``mazebot motors stop`` reads
alone, quickly, after every exit of the daemon: ``[motors]`` (:mod:`mazebot.motors_config`)
and the file's lookup and reading (:mod:`mazebot.config_file`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import typing
import warnings
from typing import Any, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic.fields import FieldInfo

from mazebot.config_file import (
    ENV_CONFIG,
    SYSTEM_CONFIG,
    config_search_path,
    default_config_path,
    read_config_file,
    validation_problems,
)
from mazebot.config_section import BcmPin, Section
from mazebot.errors import ConfigError
from mazebot.motors_config import MotorsConfig, load_motors_config
from mazebot.sim_config import CHEAP_ROBOT, SimConfig
from mazebot.slam_config import FLAT_KEYS, MAZE_CELL_M, SlamConfig

#: defined in modules of their own (the file's lookup and reading; the [motors], [sim] and [slam]
#: sections), part of this config
__all__ = [
    "CHEAP_ROBOT", "ENV_CONFIG", "MAZE_CELL_M", "SYSTEM_CONFIG", "MotorsConfig", "Section", "SimConfig",
    "SlamConfig", "config_search_path", "default_config_path", "load_motors_config", "read_config_file",
]

#: Absolute speed limits of the robot; the configured limits may not exceed them.
ABSOLUTE_MAX_SPEED_MPS = 0.5
ABSOLUTE_MAX_YAW_RATE_RADPS = 1.2

#: A robot name: one chunk of a Zenoh key expression, without its wildcards and separators (`*`, `$`, `/`).
ROBOT_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")

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

    @property
    def mount_xy_m(self) -> tuple[float, float]:
        """The lidar centre in the robot frame, (ahead, left) of the wheel axle centre."""
        return (self.mount_x_m, self.mount_y_m)

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
    cell_size_m: float = Field(
        MAZE_CELL_M, gt=0.1, lt=2.0,
        description="maze cell size (wall pitch), 1 ft; [sim] cell_size_m and slam.loop.ambiguity_shift_m follow "
        "it unless set",
    )
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
    max_drops: int = Field(
        3, ge=1, le=50,
        description="a grid frontier chosen and then left for another while still there this many times is "
        "blacklisted (counted in the explorer's choices, not in seconds)",
    )
    horizon_s: float = Field(1.2, gt=0.2, le=5.0, description="DWA rollout length")
    stuck_timeout_s: float = Field(
        4.0, gt=0.5, le=30,
        description="no progress along the path for this many seconds of planner ticks run (20 at 5 Hz; "
        "not wall time) starts a recovery",
    )
    max_recoveries: int = Field(3, ge=1, le=20, description="recoveries on one path before its goal is given up")
    stand_still_revolutions: int = Field(
        45, ge=10, le=2000,
        description="planner ticks with a new lidar revolution (~5/s) the robot may stand still with a goal "
        "before the pilot acts: first it gives the goal up, then it backs off along its own track, then it stops "
        "with a planner fault",
    )
    map_window_m: float = Field(
        0.8, gt=0.2, le=5.0, description="radius of map and wall points around the robot given to the DWA"
    )
    close_passages: bool = Field(
        True,
        description="a give-up where the local map leaves no lane for the robot's body closes that passage "
        "(a maze link, else a short segment) for the routes until the map there changes; the local planner's "
        "recoveries count per place (0.3 m) instead of per re-planned path",
    )
    hits_replace_cells: bool = Field(
        False,
        description="the local planner and its lane check take an occupied map cell that holds a hit of the "
        "latest revolution as that hit (the surface measured) instead of a disc of half the cell's diagonal",
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
    side_margin_m: float = Field(
        0.01, ge=0, le=0.1,
        description="emergency stop: free distance kept beside the commanded arc beyond the footprint (the "
        "path driven strays from the arc: the cheap robot by <= 8.7 mm in 97.5 % of its stopping distances)",
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
        True,
        description="on the real clock, run the motor control loop in a process of its own (its own interpreter "
        "lock: a due tick never waits for the main process), where the motor driver can be opened there; "
        "else the thread",
    )
    control_rt_priority: int = Field(
        10,
        ge=0,
        le=99,
        description="SCHED_FIFO priority of the control process, so a due tick runs ahead of SLAM and the planner "
        "(needs CAP_SYS_NICE or systemd's LimitRTPRIO=; refused, it falls back to control_nice); 0: not asked",
    )
    control_nice: int = Field(
        -10,
        ge=-20,
        le=0,
        description="nice value of the control process when SCHED_FIFO is refused (needs LimitNICE=); 0: not asked",
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


class DeprecatedKeyWarning(FutureWarning):
    """A config file uses a key of an older layout; it still works, under its new name."""


def _migrate(data: dict[str, Any], source: str) -> dict[str, Any]:
    """``data`` with the flat ``[slam]`` keys of the old layout moved to their nested sections.

    One :class:`DeprecatedKeyWarning` per moved key names the old and the new key. A key
    given both ways is an error: which one was meant is not for us to guess.
    """
    slam = data.get("slam")
    if not isinstance(slam, dict) or not any(key in FLAT_KEYS for key in slam):
        return data
    slam = {key: (dict(value) if isinstance(value, dict) else value) for key, value in slam.items()}
    for old in [key for key in slam if key in FLAT_KEYS]:
        section, key = FLAT_KEYS[old].split(".")
        table = slam.setdefault(section, {})
        if not isinstance(table, dict):
            continue  # validation names the section that is not a table
        if key in table:
            raise ConfigError(
                f"{source}: slam.{old} and slam.{section}.{key} are the same key: keep slam.{section}.{key}"
            )
        table[key] = slam.pop(old)
        warnings.warn(
            f"{source}: slam.{old} is now slam.{section}.{key} (the old name still works; "
            "`mazebot config defaults` shows the new layout)",
            DeprecatedKeyWarning,
            stacklevel=3,
        )
    return {**data, "slam": slam}


def _one_maze_pitch(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with the maze's pitch as one key, ``[planner] cell_size_m``: the simulated maze's cells and
    the loop closures' ambiguity shift (one cell) follow it unless the file sets them."""
    planner = data.get("planner")
    pitch = planner.get("cell_size_m") if isinstance(planner, dict) else None
    if pitch is None:
        return data
    sim, slam = data.get("sim", {}), data.get("slam", {})
    loop = slam.get("loop", {}) if isinstance(slam, dict) else None
    if not isinstance(sim, dict) or not isinstance(loop, dict):
        return data  # validation names the section that is not a table
    loop = {"ambiguity_shift_m": pitch, **loop}
    return {**data, "sim": {"cell_size_m": pitch, **sim}, "slam": {**slam, "loop": loop}}


def parse_config(data: dict[str, Any], source: str = "<config>") -> Config:
    """Validate a parsed TOML document; raise ConfigError with one line per problem.

    Keys of the old flat ``[slam]`` layout are moved to their sections first
    (:data:`mazebot.slam_config.FLAT_KEYS`), with a :class:`DeprecatedKeyWarning` each, and
    the keys that follow ``[planner] cell_size_m`` are filled in (:func:`_one_maze_pitch`).
    """
    data = _one_maze_pitch(_migrate(data, source))
    try:
        # strict: TOML has real types, so "8080" or true for a port is a mistake, not a port; in JSON
        # mode, because pydantic's Python strict mode takes only instances for the nested dataclass sections
        text = json.dumps(data, default=str)
    except ValueError as exc:  # a float nan or inf, which no section takes
        raise ConfigError(f"{source}: {exc}") from None
    try:
        return Config.model_validate_json(text, strict=True)
    except ValidationError as exc:
        raise validation_problems(exc, source) from None


def config_from_json(text: str, source: str = "<config>") -> Config:
    """A config saved as JSON (``Config.model_dump_json``: recordings, saved runs), of any layout.

    An old layout is moved to the new one without warnings: a recording is not the user's file to fix.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecatedKeyWarning)
        return parse_config(json.loads(text), source)


def load_config(path: str | os.PathLike[str] | None = None) -> Config:
    """Load and validate a config file; with no path, the file :func:`default_config_path` finds, or the defaults."""
    if path is None:
        path = default_config_path()
        if path is None:
            return Config()
    return parse_config(read_config_file(path), str(path))


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
    for name in Config.model_fields:
        lines.extend(_render_section(name, getattr(config, name)))
    return "\n".join(lines) + "\n"


def _section_fields(section: object) -> dict[str, Any]:
    """The fields (pydantic ``FieldInfo``) of a section: a model, or a dataclass with pydantic metadata."""
    if isinstance(section, BaseModel):
        return dict(type(section).model_fields)
    hints = typing.get_type_hints(type(section), include_extras=True)
    infos = {}
    for f in dataclasses.fields(section):  # type: ignore[arg-type]
        metadata = getattr(hints[f.name], "__metadata__", ())
        infos[f.name] = next((m for m in metadata if isinstance(m, FieldInfo)), FieldInfo())
    return infos


def _is_section(value: object) -> bool:
    return isinstance(value, BaseModel) or (dataclasses.is_dataclass(value) and not isinstance(value, type))


def _render_section(name: str, section: object) -> list[str]:
    """``[name]`` with its keys, each after its description, then its nested sections as ``[name.sub]``."""
    lines = ["", f"# {(type(section).__doc__ or '').strip().splitlines()[0]}", f"[{name}]"]
    nested = []
    for key, info in _section_fields(section).items():
        value = getattr(section, key)
        if _is_section(value):
            nested.append((key, value))
            continue
        if info.description:
            lines.append(f"# {info.description}")
        lines.append(f"{key} = {_toml_value(value)}")
    for key, value in nested:
        lines.extend(_render_section(f"{name}.{key}", value))
    return lines
