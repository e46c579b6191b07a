"""What a loop-closure submap could have seen: the area its keyframes' beams covered.

A loop closure's inlier ratio (the share of the new scan's points that found a wall of
the candidate's submap within ICP's gate) measures agreement only where the two views
overlap. In a maze the submap and the new scan see the same few cells; in a building
with a scan every metre they do not: the new scan looks through a doorway the old
keyframes passed with the door behind them, sees the far side of a corridor they saw
end-on, or the half of the room behind a 180° laser. Those points have nothing to match
however right the alignment is, and the plain ratio rejects the closure as "low inlier
ratio" (most of the rejections on the real logs).

So the ratio is also taken among the points the submap could have matched: a point is
*observable* if some keyframe of the submap had a beam towards it (within its angular
coverage) that reached at least as far as the point, less a margin (the wall that ended
the beam is observed; a point behind it is not). Each keyframe's beams (``ray_ends``,
the same rays the occupancy grid is built from, no-return beams included: they saw free
space up to their end) are sorted by bearing; a query point takes the beam nearest in
bearing, and that beam must be within twice the keyframe's median beam spacing (else
the point lies outside the field of view, or in a gap of dropped beams).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mazebot.geometry import transform_points


@dataclass(frozen=True)
class BeamFan:
    """One keyframe's beams in a common frame: the lidar's position, beam bearings (sorted) and lengths."""

    origin_xy: np.ndarray
    bearing_rad: np.ndarray
    length_m: np.ndarray
    max_gap_rad: float

    @classmethod
    def from_rays(cls, pose: np.ndarray, sensor_xy: np.ndarray, ray_ends: np.ndarray) -> BeamFan | None:
        """The fan of rays ``sensor_xy → ray_ends`` (robot frame) of a keyframe at ``pose`` (the common frame)."""
        ends = np.asarray(ray_ends, dtype=np.float64).reshape(-1, 2)
        if ends.shape[0] < 2:
            return None
        sensor = np.asarray(sensor_xy, dtype=np.float64).reshape(1, 2)
        origin = transform_points(pose, sensor)[0]
        world = transform_points(pose, ends)
        d = world - origin
        bearing = np.arctan2(d[:, 1], d[:, 0])
        order = np.argsort(bearing, kind="stable")
        bearing = bearing[order]
        spacing = np.diff(bearing)
        spacing = spacing[spacing > 1e-9]
        gap = 2.0 * float(np.median(spacing)) if spacing.size else math.radians(2.0)
        return cls(origin, bearing, np.hypot(d[order, 0], d[order, 1]), gap)

    def sees(self, points: np.ndarray, margin_m: float) -> np.ndarray:
        """(N,) bool: a beam of this fan reached ``points`` (N, 2) or beyond, less ``margin_m``."""
        d = points - self.origin_xy
        bearing = np.arctan2(d[:, 1], d[:, 0])
        rng = np.hypot(d[:, 0], d[:, 1])
        n = self.bearing_rad.shape[0]
        right = np.searchsorted(self.bearing_rad, bearing) % n
        left = (right - 1) % n
        gap_r = np.abs(np.remainder(self.bearing_rad[right] - bearing + math.pi, math.tau) - math.pi)
        gap_l = np.abs(np.remainder(self.bearing_rad[left] - bearing + math.pi, math.tau) - math.pi)
        nearest = np.where(gap_r <= gap_l, right, left)
        gap = np.minimum(gap_r, gap_l)
        return (gap <= self.max_gap_rad) & (rng <= self.length_m[nearest] + margin_m)


@dataclass(frozen=True)
class ObservedArea:
    """The union of a submap's beam fans (:class:`BeamFan`), in the submap's frame."""

    fans: tuple[BeamFan, ...]

    @classmethod
    def from_keyframes(
        cls, poses: Sequence[np.ndarray], sensors_xy: Sequence[np.ndarray], rays: Sequence[np.ndarray]
    ) -> ObservedArea:
        fans = (BeamFan.from_rays(p, s, r) for p, s, r in zip(poses, sensors_xy, rays, strict=True))
        return cls(tuple(f for f in fans if f is not None))

    def contains(self, points: np.ndarray, margin_m: float) -> np.ndarray:
        """(N,) bool: some keyframe of the submap had a beam reaching each point (N, 2), within ``margin_m``."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        seen = np.zeros(pts.shape[0], dtype=bool)
        for fan in self.fans:
            rest = ~seen
            if not rest.any():
                break
            seen[rest] = fan.sees(pts[rest], margin_m)
        return seen
