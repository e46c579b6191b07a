"""Odometry with the errors of a real differential-drive robot, derived from reference poses.

White noise per increment (:func:`mazebot.slam.slam_cli.noisy_odometry`) averages out
over many steps; real wheel odometry does not. Its errors are mostly **systematic**
(Borenstein & Feng, "Measurement and correction of systematic odometry errors in mobile
robots", IEEE Trans. Robotics and Automation 12(6), 1996, the UMBmark paper): the two
wheels' effective diameters differ from the nominal one (``E_d``) and the effective
track width from the configured one (``E_b``). Each scan increment of the reference path
is split into the arc lengths of the two wheels,

    d_r = d + b·dθ/2,    d_l = d − b·dθ/2

(Siegwart, Nourbakhsh & Scaramuzza, *Introduction to Autonomous Mobile Robots*, 2nd ed.,
section 5.2.4), which the encoders measure scaled, ``(1 + e_r)·d_r`` and ``(1 + e_l)·d_l``,
and which dead reckoning turns back into a step with its believed track width
``b·(1 + e_b)``. So a straight metre comes out ``1 + (e_l + e_r)/2`` long and turned by
``(e_r − e_l)/b'``, an in-place turn scaled by ``(1 + (e_l + e_r)/2)/(1 + e_b)``: a
heading that drifts in every straight run and is wrong after every turn. On top of it
a **heading bias that drifts** (the floor, tyre pressure and load change along a run):
``β`` radians per metre travelled, drawn at the start and then a random walk,
``β ← β + N(0, σ_walk²·d)``. White noise (``--odom-noise``) is added last. Every draw
comes from one seeded generator: the same seed, the same odometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mazebot.errors import UsageError
from mazebot.geometry import compose, relative_pose


@dataclass(frozen=True)
class SystematicOdometryModel:
    """Standard deviations of the drawn errors (each drawn once per run, except the walk).

    Defaults: a robot whose wheels were never calibrated: 1 % per wheel (UMBmark found
    ``E_d`` up to 1–2 % on factory robots), 2 % of the track width (the contact points of
    wide tyres), a heading bias of 0.005 rad/m that wanders by 0.002 rad per √m;
    ``track_width_m`` is the nominal track (a Pioneer-class robot of the CARMEN logs).
    """

    wheel_scale_std: float = 0.01
    track_scale_std: float = 0.02
    bias_rad_per_m_std: float = 0.005
    bias_walk_rad_per_m_per_sqrt_m: float = 0.002
    track_width_m: float = 0.4

    def __post_init__(self) -> None:
        values = (self.wheel_scale_std, self.track_scale_std, self.bias_rad_per_m_std,
                  self.bias_walk_rad_per_m_per_sqrt_m)
        if not all(math.isfinite(v) and v >= 0 for v in values):
            raise UsageError(f"systematic odometry errors must be finite and >= 0, got {values}")
        if not self.track_width_m > 0:
            raise UsageError(f"the track width must be positive, got {self.track_width_m}")

    def draw(self, rng: np.random.Generator) -> DrawnErrors:
        """This run's wheel and track errors and initial heading bias."""
        e = rng.standard_normal(4)
        return DrawnErrors(
            left_scale=float(e[0] * self.wheel_scale_std),
            right_scale=float(e[1] * self.wheel_scale_std),
            track_scale=float(e[2] * self.track_scale_std),
            initial_bias_rad_per_m=float(e[3] * self.bias_rad_per_m_std),
        )


@dataclass(frozen=True)
class DrawnErrors:
    """One run's systematic errors: wheel scales ``e_l``, ``e_r``, track scale ``e_b``, bias ``β₀`` (rad/m)."""

    left_scale: float
    right_scale: float
    track_scale: float
    initial_bias_rad_per_m: float


def systematic_odometry(
    poses: np.ndarray,
    model: SystematicOdometryModel,
    white: tuple[float, float],
    rng: np.random.Generator,
) -> tuple[np.ndarray, DrawnErrors, np.ndarray]:
    """Odometry poses (N, 3) from reference poses, with ``model``'s errors and ``white`` noise.

    Returns ``(odometry, drawn errors, heading bias (N,) in rad/m at each step)``; the
    odometry frame starts at the origin. ``white`` is ``(σ_xy per m, σ_θ per m + rad)``
    as ``--odom-noise``.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    drawn = model.draw(rng)
    b = model.track_width_m
    believed_b = b * (1.0 + drawn.track_scale)
    out = np.zeros_like(poses)
    bias = np.zeros(poses.shape[0])
    beta = drawn.initial_bias_rad_per_m
    for k in range(1, poses.shape[0]):
        inc = relative_pose(poses[k - 1], poses[k])
        dist = math.hypot(inc[0], inc[1])
        d = math.copysign(dist, inc[0]) if inc[0] else dist  # driving backwards: negative arc
        dth = float(inc[2])
        left = (1.0 + drawn.left_scale) * (d - 0.5 * b * dth)
        right = (1.0 + drawn.right_scale) * (d + 0.5 * b * dth)
        d_meas = 0.5 * (left + right)
        dth_meas = (right - left) / believed_b + beta * dist
        # the step's direction relative to its heading is kept (a lateral slide stays one)
        scale = d_meas / d if d else 0.0
        step = np.array([inc[0] * scale, inc[1] * scale, dth_meas])
        step += rng.standard_normal(3) * np.array([white[0] * dist, white[0] * dist, white[1] * (dist + abs(dth))])
        out[k] = compose(out[k - 1], step)
        beta += rng.standard_normal() * model.bias_walk_rad_per_m_per_sqrt_m * math.sqrt(dist)
        bias[k] = beta
    return out, drawn, bias


def parse_systematic(text: str | None) -> SystematicOdometryModel:
    """``--odom-systematic WHEEL,TRACK,BIAS,WALK`` (standard deviations; see the model), default if None."""
    if text is None:
        return SystematicOdometryModel()
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4:
        raise UsageError(
            f"--odom-systematic expects WHEEL,TRACK,BIAS,WALK like 0.01,0.02,0.005,0.002, got {text!r}"
        )
    try:
        return SystematicOdometryModel(*values)
    except UsageError as error:
        raise UsageError(f"--odom-systematic: {error}") from None
