"""Wheel sizes, track width and lidar yaw from encoder counts and scan-matched motions.

Every run of the calibration is a motion the lidar measured by matching the still scan
after it against the still scan before it (``x, y, θ`` of the robot frame after, in the
frame before) together with the encoder counts of both wheels. With ``k_l, k_r`` the
metres per count of each wheel and ``L`` the track width, the wheel travels are
``d = k·c`` and a differential drive moves along a circular arc (Siegwart, Nourbakhsh &
Scaramuzza, *Introduction to Autonomous Mobile Robots*, 2nd ed., 5.2.4)::

    (d_l + d_r) / 2 = s        (arc length of the axle centre)
    d_r − d_l       = L · Δθ

A straight run gives both equations, ``s`` from its chord ``|t|`` as ``s = |t|·(Δθ/2) /
sin(Δθ/2)``; a turn in place gives the second. Together they are linear in
``(k_l, k_r, L)``: least squares over all runs. This is UMBmark's pair of unknowns
(Borenstein & Feng, "Measurement and correction of systematic odometry errors in mobile
robots", IEEE T-RA 12(6), 1996: unequal wheel diameters E_d and the wheelbase error
E_b), with the lidar as the ruler instead of a tape measure.

Lidar yaw: a straight run's chord lies at ``Δθ/2`` from the heading it started with
(forward) or at ``π + Δθ/2`` (backward); a lidar turned by ``e`` on its mount sees the
chord at that angle minus ``e``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mazebot.errors import MazebotError


class CalibrationError(MazebotError):
    """A calibration step could not measure what it needs; the message names the step and why."""


@dataclass(frozen=True)
class Run:
    """One measured motion: encoder counts (forward positive, after the wiring fix) and the scan match."""

    kind: str  # "straight" or "turn"
    left_counts: int
    right_counts: int
    x_m: float
    y_m: float
    theta_rad: float


@dataclass(frozen=True)
class Geometry:
    """What :func:`solve_geometry` finds: metres per count of each wheel and the track width."""

    left_m_per_count: float
    right_m_per_count: float
    track_width_m: float
    worst_arc_residual: float  # largest |arc from encoders / arc from scans − 1| of the straight runs


def arc_length_m(run: Run) -> float:
    """Signed arc length of the axle centre from a straight run's chord (negative backward)."""
    chord_m = math.hypot(run.x_m, run.y_m)
    half = 0.5 * run.theta_rad
    arc_m = chord_m if abs(half) < 1e-9 else chord_m * half / math.sin(half)
    return math.copysign(arc_m, run.left_counts + run.right_counts)


def solve_geometry(runs: list[Run]) -> Geometry:
    """Least-squares ``(k_l, k_r, L)`` over straight runs and turns (module docstring)."""
    rows: list[list[float]] = []
    rhs: list[float] = []
    straight = [r for r in runs if r.kind == "straight"]
    if not straight or not any(r.kind == "turn" for r in runs):
        raise ValueError("geometry needs at least one straight run and one turn")
    for run in runs:
        if run.kind == "straight":
            rows.append([0.5 * run.left_counts, 0.5 * run.right_counts, 0.0])
            rhs.append(arc_length_m(run))
        rows.append([-float(run.left_counts), float(run.right_counts), -run.theta_rad])
        rhs.append(0.0)
    solution, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
    k_l, k_r, track_m = (float(v) for v in solution)
    worst = max(
        abs(0.5 * (k_l * r.left_counts + k_r * r.right_counts) / arc_length_m(r) - 1.0) for r in straight
    )
    return Geometry(k_l, k_r, track_m, worst)


def yaw_error_rad(runs: list[Run]) -> float:
    """How far the lidar is turned on its mount beyond what the scans were corrected for (mean over runs)."""
    errors = []
    for run in runs:
        if run.kind != "straight":
            continue
        backward = run.left_counts + run.right_counts < 0
        expected = 0.5 * run.theta_rad + (math.pi if backward else 0.0)
        errors.append(math.remainder(expected - math.atan2(run.y_m, run.x_m), math.tau))
    if not errors:
        raise ValueError("the lidar's yaw needs at least one straight run")
    return float(np.mean(errors))


@dataclass(frozen=True)
class Pulse:
    """One motor output driven forward on its own: which encoder counted, what the lidar saw."""

    output: str  # "left" or "right": the side [motors] assigns the channel to
    left_counts: int  # the encoder on the configured left pins (after the configured inversion)
    right_counts: int
    x_m: float
    y_m: float
    theta_rad: float


@dataclass(frozen=True)
class Wiring:
    """Per wheel: which motor output drives it and whether forward needs the opposite throttle;
    which encoder input counts it and whether that count runs backwards."""

    wheel_of_output: dict[str, str]  # output side -> wheel it drives
    output_reversed: dict[str, bool]  # output side -> a positive throttle turns its wheel backwards
    wheel_of_encoder: dict[str, str]  # encoder input side -> wheel it counts
    encoder_reversed: dict[str, bool]  # encoder input side -> counts down when its wheel turns forward


#: A pulse that moved the robot less than this (lidar) or counted fewer ticks did not turn its wheel.
MIN_PULSE_TURN_RAD = math.radians(2.0)
MIN_PULSE_COUNTS = 20


def deduce_wiring(pulses: list[Pulse]) -> Wiring:
    """Wiring from one forward pulse of each output (a wheel turned alone pivots the robot on the other).

    The left wheel turning forward alone turns the robot clockwise and moves it forward;
    the right one counter-clockwise and forward. Backwards, both signs flip: so the sign
    of the forward motion says which way the wheel turned, and the sign of the turn times
    it says which wheel it is. The encoder that counted is that wheel's.
    """
    wheel_of_output: dict[str, str] = {}
    output_reversed: dict[str, bool] = {}
    wheel_of_encoder: dict[str, str] = {}
    encoder_reversed: dict[str, bool] = {}
    for p in pulses:
        if abs(p.theta_rad) < MIN_PULSE_TURN_RAD:
            counted = max(abs(p.left_counts), abs(p.right_counts))
            why = f"encoders counted {counted}" if counted >= MIN_PULSE_COUNTS else "no encoder counted either"
            raise CalibrationError(
                f"wiring: the {p.output} motor output did not move the robot (lidar saw "
                f"{math.degrees(p.theta_rad):.1f}°, {why}): a wheel does not turn; check that motor's wiring and power"
            )
        forward = p.x_m > 0
        wheel = "left" if (p.theta_rad < 0) == forward else "right"
        if wheel in wheel_of_output.values():
            raise CalibrationError(f"wiring: both motor outputs turn the {wheel} wheel; check the motor channels")
        wheel_of_output[p.output] = wheel
        output_reversed[p.output] = not forward
        counts = {"left": p.left_counts, "right": p.right_counts}
        encoder = max(counts, key=lambda side: abs(counts[side]))
        other = "right" if encoder == "left" else "left"
        if abs(counts[encoder]) < MIN_PULSE_COUNTS:
            raise CalibrationError(
                f"wiring: the {wheel} wheel turned but no encoder counted it ({counts[encoder]} counts): "
                "check its encoder's wiring and [encoders] pins"
            )
        if abs(counts[other]) > 0.2 * abs(counts[encoder]):
            raise CalibrationError(
                f"wiring: both encoders counted while only the {wheel} wheel turned ({p.left_counts}, "
                f"{p.right_counts}): are the encoder pins shared or crossed?"
            )
        if encoder in wheel_of_encoder:
            raise CalibrationError(f"wiring: the {encoder} encoder input counted both wheels; check [encoders] pins")
        wheel_of_encoder[encoder] = wheel
        # counts are signed as the wheel's motion: forward motion with positive counts is right
        encoder_reversed[encoder] = (counts[encoder] > 0) != forward
    return Wiring(wheel_of_output, output_reversed, wheel_of_encoder, encoder_reversed)
