"""Differential-drive dead reckoning from wheel encoder ticks.

Each update turns the tick increments of both wheels into travelled arc lengths
``d_l, d_r`` and integrates the exact circular arc between them (Siegwart, Nourbakhsh &
Scaramuzza, *Introduction to Autonomous Mobile Robots*, 2nd ed., section 5.2.4):

    d = (d_r + d_l) / 2,    dθ = (d_r - d_l) / b
    x += d · sinc-corrected cos(θ + dθ/2),  y += ... sin(θ + dθ/2),  θ += dθ

where ``b`` is the track width. The midpoint-heading form with the chord factor
``sin(dθ/2) / (dθ/2)`` is exact for a constant-curvature step.

A gearbox with play between the encoder's shaft and the wheel (backlash) counts, after
every reversal of a wheel, up to the play's angle of travel the wheel never made. With
``backlash_rad`` given, each wheel's counted travel goes first into taking up the play and
only the rest moves the wheel: the dead-band (hysteresis) model of backlash (Nordin &
Gutman, "Controlling mechanical systems with backlash: a survey", Automatica 38, 2002,
section 2), the play starting centred.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class OdometryPose:
    x_m: float = 0.0
    y_m: float = 0.0
    theta_rad: float = 0.0
    distance_m: float = 0.0  # total path length travelled by the axle centre


def wheel_metres_per_tick(
    ticks_per_rev: int, wheel_diameter_m: float, diameter_ratio: float = 1.0
) -> tuple[float, float]:
    """Distance (left, right) a wheel's rim travels per counted tick.

    Unequal wheels (UMBmark's E_d, Borenstein and Feng 1996): ``wheel_diameter_m`` is
    their mean and ``diameter_ratio`` the right's diameter over the left's. The odometry
    and the wheel speed controller both take their distances from here, so a calibrated
    ratio drives the wheels at the speeds the odometry will measure.
    """
    mean_m = math.pi * wheel_diameter_m / ticks_per_rev
    return mean_m * 2.0 / (1.0 + diameter_ratio), mean_m * 2.0 * diameter_ratio / (1.0 + diameter_ratio)


class DiffDriveOdometry:
    """Integrates wheel ticks into a pose.

    Example::

        odo = DiffDriveOdometry(ticks_per_rev=1440, wheel_diameter_m=0.065, track_width_m=0.15)
        odo.update(left_ticks=1440, right_ticks=1440)   # one wheel turn straight ahead
        odo.pose.x_m  # ≈ 0.204
    """

    def __init__(
        self, ticks_per_rev: int, wheel_diameter_m: float, track_width_m: float, diameter_ratio: float = 1.0,
        backlash_rad: float = 0.0,
    ) -> None:
        if ticks_per_rev <= 0 or wheel_diameter_m <= 0 or track_width_m <= 0 or diameter_ratio <= 0:
            raise ValueError("ticks_per_rev, wheel_diameter_m, track_width_m and diameter_ratio must be positive")
        if backlash_rad < 0:
            raise ValueError(f"backlash_rad must be >= 0, got {backlash_rad!r}")
        self.metres_per_tick = math.pi * wheel_diameter_m / ticks_per_rev
        self.metres_per_tick_left, self.metres_per_tick_right = wheel_metres_per_tick(
            ticks_per_rev, wheel_diameter_m, diameter_ratio
        )
        self.track_width_m = track_width_m
        self.pose = OdometryPose()
        self._last: tuple[int, int] | None = None
        #: half the play as rim travel (m): the shaft moves this far either way before the wheel follows
        self.half_play_m = 0.5 * backlash_rad * 0.5 * wheel_diameter_m
        self._play_m = [0.0, 0.0]  # each wheel's shaft ahead of it within the play (m of rim travel)

    def update(self, left_ticks: int, right_ticks: int) -> tuple[float, float]:
        """Advance the pose to these cumulative tick counts; returns (d_left_m, d_right_m)."""
        if self._last is None:
            self._last = (left_ticks, right_ticks)
            return 0.0, 0.0
        d_left_m = self._through_play(0, (left_ticks - self._last[0]) * self.metres_per_tick_left)
        d_right_m = self._through_play(1, (right_ticks - self._last[1]) * self.metres_per_tick_right)
        self._last = (left_ticks, right_ticks)
        self.integrate(d_left_m, d_right_m)
        return d_left_m, d_right_m

    def _through_play(self, wheel: int, counted_m: float) -> float:
        """The wheel's own travel (m) when its shaft turned ``counted_m``: what the play takes up is lost."""
        if self.half_play_m <= 0.0:
            return counted_m
        play_m = min(max(self._play_m[wheel] - counted_m, -self.half_play_m), self.half_play_m)
        moved_m = counted_m + play_m - self._play_m[wheel]
        self._play_m[wheel] = play_m
        return moved_m

    def integrate(self, d_left_m: float, d_right_m: float) -> None:
        """Move the pose along the arc the two wheel travels describe."""
        d_m = 0.5 * (d_left_m + d_right_m)
        d_theta = (d_right_m - d_left_m) / self.track_width_m
        half = 0.5 * d_theta
        chord = 1.0 if abs(half) < 1e-9 else math.sin(half) / half
        p = self.pose
        heading = p.theta_rad + half
        p.x_m += d_m * chord * math.cos(heading)
        p.y_m += d_m * chord * math.sin(heading)
        p.theta_rad = math.remainder(p.theta_rad + d_theta, math.tau)
        p.distance_m += abs(d_m)
