"""The ``[sim]`` section: the simulated robot and world of ``mazebot run --sim`` and ``mazebot bench``.

The harness's own knobs (which world, which maze, how a hand-built maze errs, how the
robot's parts are imperfect, which lidar the emulator is), apart from the product's
sections in :mod:`mazebot.config`, of which it is one: the daemon's tasks never read it;
the simulator, the benchmark and the commands that start them (``--sim``) do.
:data:`CHEAP_ROBOT` is the preset ``robot_build = "cheap"`` applies to the other sections
too (:class:`mazebot.config.Config` fills it in).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from mazebot.config_section import Section
from mazebot.slam_config import MAZE_CELL_M


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
    cell_size_m: float = Field(
        MAZE_CELL_M, gt=0.1, le=2.0, description="maze cell size; unless set, [planner] cell_size_m (1 ft)"
    )
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
