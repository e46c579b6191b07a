"""Scan preparation: one raw lidar revolution in, the point sets SLAM matches and maps out.

The steps, in the order :func:`prepare_scan` runs them:

1. **Range gate.** Drop samples the driver flagged invalid or closer than
   ``min_range_m``. Valid returns farther than ``max_range_m`` are kept apart as
   *no-return beams*: they say "free at least this far" and clear space in the map, but
   they are never matched and never mark a wall.
2. **Impulse rejection.** A running median along the scan (Tukey's running median, the
   median filtering of Vinch, *Design and Implementation of an Intelligent Primitive
   Driver*, MS thesis, U. Florida, 2003) over ``median_window`` neighbouring in-range
   samples. A sample is *rejected* when it differs from its local median by more than
   ``impulse_abs_m + impulse_rel * median``; nothing is smoothed, so straight walls, corners
   and steps keep their exact ranges (the median of a monotonic run is the sample itself).
   Only isolated spikes, which the A1 produces on glossy or black surfaces, go.
3. **De-skew.** The A1 turns at ~5.5 rev/s, so a robot at 0.3 m/s moves ~5 cm during
   one revolution. Each sample ``i`` was measured from the pose ``T(t_i)``; it is
   expressed in the robot frame of the revolution's *end* pose:
   ``p_end = T(t_end)⁻¹ ∘ T(t_i) ∘ T_mount ∘ p_lidar`` (the motion compensation of
   KISS-ICP, Vizzo et al., RA-L 2023, section III.A, with odometry instead of a
   constant-velocity model).
4. **Downsample for matching.** A voxel grid keeps, in each ``voxel_size_m`` square,
   the original point nearest the square's centre (KISS-ICP keeps an original point
   rather than a centroid, so no phantom points appear at corners). Not the first point
   in scan order: which sample of a wall comes first in a voxel depends on its range
   noise and on the direction the head turns, and keeping it biased the matched
   heading by ~0.04° per scan at 1 % range noise, which chains into degrees of drift.
   The full point set stays for the map.

Frames: the lidar frame is :class:`~mazebot.io.scan.Scan`'s (CCW, 0 = the lidar's front
mark); the robot frame has x forward, y left, origin at the wheel axle centre; the
mounting offset ``(mount_x_m, mount_y_m, mount_yaw_rad)`` places the lidar in it. The
RPLidar driver already adds the mount yaw to its angles, so only the position offset is
left to apply to its scans.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from mazebot.config import LidarConfig
from mazebot.geometry import transform_points
from mazebot.io.scan import Scan
from mazebot.slam_config import PrepareSection

_LIDAR = LidarConfig()  # the lidar's defaults, written once in [lidar]

#: Pose look-up: sample times (s) -> (x_m, y_m, theta_rad) arrays in any fixed frame
#: (the odometry frame). :meth:`mazebot.sim.lidar_samples.PoseHistory.at` has this shape.
PoseAtTime = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class PrepareParams(PrepareSection):
    """Parameters of :func:`prepare_scan`: the ``[slam.prepare]`` section and the lidar's range and mounting.

    The lidar's values default to ``[lidar]``'s; ``from_config`` in ``mazebot.slam.slam``
    fills in the configured ones.
    """

    min_range_m: float = _LIDAR.min_range_m
    mount_x_m: float = _LIDAR.mount_x_m  # lidar centre ahead of the axle centre
    mount_y_m: float = _LIDAR.mount_y_m  # lidar centre left of the axle centre
    # robot-frame angle (CCW) of the lidar's 0 mark; leave 0 for scans from mazebot.io.rplidar,
    # whose angles already include the configured mount yaw
    mount_yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0.0 <= self.min_range_m < self.max_range_m:
            raise ValueError(f"need 0 <= min_range_m < max_range_m, got {self.min_range_m}, {self.max_range_m}")


@dataclass(frozen=True)
class Beams:
    """Rays for the occupancy grid: where each starts, where it ends, whether it hit.

    ``endpoints`` and ``origins`` are (K, 2) metres in one frame (robot or world);
    ``hit`` (K,) is False for no-return beams, which only clear free space.
    ``sensor_pose`` (3,) is the lidar's pose at the end of the revolution in that frame.
    Pass to :meth:`mazebot.slam.grid.OccupancyGrid.integrate` as
    ``grid.integrate(b.sensor_pose, b.endpoints, b.hit, b.origins)``.
    """

    sensor_pose: np.ndarray
    endpoints: np.ndarray
    hit: np.ndarray
    origins: np.ndarray


@dataclass(frozen=True)
class PreparedScan:
    """One revolution ready for SLAM, everything in the robot frame at ``time_s``.

    ``points_full`` (N, 2) are all kept hits (for the map), ``points_match`` (M, 2) the
    voxel-downsampled subset (for ICP). ``origins_full`` (N, 2) is the lidar centre at
    each hit's own sample time (de-skewed rays start there). ``free_endpoints`` and
    ``free_origins`` (K, 2) are the no-return beams, ended at ``max_range_m``.
    ``angle_rad``/``range_m`` (N,) are the kept hits as measured, in the lidar frame.
    ``sensor_xy`` (2,) is the lidar centre at ``time_s`` (the mounting offset).
    ``index`` (N,) are the hits' positions in the original :class:`Scan`.
    """

    points_full: np.ndarray
    points_match: np.ndarray
    origins_full: np.ndarray
    free_endpoints: np.ndarray
    free_origins: np.ndarray
    angle_rad: np.ndarray
    range_m: np.ndarray
    time_s: float
    sensor_xy: np.ndarray
    index: np.ndarray
    sensor_yaw_rad: float = 0.0
    rejected_impulses: int = 0  # samples removed by the median test

    def beams(self) -> Beams:
        """Hits and no-return beams as rays in the robot frame."""
        n, k = self.points_full.shape[0], self.free_endpoints.shape[0]
        return Beams(
            sensor_pose=np.array([self.sensor_xy[0], self.sensor_xy[1], self.sensor_yaw_rad]),
            endpoints=np.concatenate((self.points_full, self.free_endpoints)),
            hit=np.concatenate((np.ones(n, dtype=bool), np.zeros(k, dtype=bool))),
            origins=np.concatenate((self.origins_full, self.free_origins)),
        )

    def beams_world(self, pose: np.ndarray) -> Beams:
        """The rays in the world frame, for the robot at ``pose`` (x_m, y_m, theta_rad) at ``time_s``."""
        b = self.beams()
        pose = np.asarray(pose, dtype=np.float64)
        sensor = transform_points(pose, b.sensor_pose[None, :2])[0]
        return Beams(
            sensor_pose=np.array([sensor[0], sensor[1], pose[2] + self.sensor_yaw_rad]),
            endpoints=transform_points(pose, b.endpoints),
            hit=b.hit,
            origins=transform_points(pose, b.origins),
        )


def impulse_mask(range_m: np.ndarray, window: int, abs_m: float, rel: float, circular: bool) -> np.ndarray:
    """True for samples that agree with the running median of their ``window`` neighbours.

    Vectorized: a (N, window) strided view, one ``np.median`` over its rows. ``circular``
    wraps the ends (a full lidar turn); otherwise the ends are padded with their own
    value, which never rejects them.
    """
    n = range_m.shape[0]
    if window < 3 or n < window:
        return np.ones(n, dtype=bool)
    half = window // 2
    padded = np.pad(range_m, half, mode="wrap" if circular else "edge")
    if window == 3:  # the default: the median of three in min/max form (exactly np.median's, ~10x faster)
        a, b, c = padded[:-2], padded[1:-1], padded[2:]
        median = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
    else:
        median = np.median(sliding_window_view(padded, window), axis=1)
    return np.abs(range_m - median) <= abs_m + rel * median


#: The voxel filter takes one array slot per voxel of the points' bounding box when the box
#: holds at most this many voxels per point (a submap of a 16×16 maze at 1 cm: ~20); wider
#: boxes (a building's laser log) sort instead. Both give the same points.
DENSE_VOXELS_PER_POINT = 64


def voxel_downsample(points_xy: np.ndarray, voxel_size_m: float) -> np.ndarray:
    """Indices of the point nearest the centre of each ``voxel_size_m`` square, in their original order.

    The choice depends only on where each point lies in its voxel, never on the order
    of the samples (see step 4 of the module docstring); of points equally near the
    centre the first wins. The submap is rebuilt from ~12 000 points at every keyframe,
    so this runs in a few vectorised passes over a dense array of the bounding box's
    voxels (no sort) where that box is small, and with a sort by voxel otherwise.
    """
    n = points_xy.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    scaled = points_xy / voxel_size_m
    floor = np.floor(scaled)
    cells = floor.astype(np.int64)
    # column by column: numpy's reductions along a length-2 axis cost ten times as much
    dx, dy = scaled[:, 0] - floor[:, 0] - 0.5, scaled[:, 1] - floor[:, 1] - 0.5
    off_centre = dx * dx + dy * dy
    cx, cy = cells[:, 0], cells[:, 1]
    x0, y0 = int(cx.min()), int(cy.min())
    width, height = int(cx.max()) - x0 + 1, int(cy.max()) - y0 + 1
    if width * height <= DENSE_VOXELS_PER_POINT * max(n, 64):
        return _nearest_centre_dense((cx - x0) * height + (cy - y0), width * height, off_centre)
    # one int64 key per cell: 32 bits per axis covers +-2^31 voxels, far beyond any map
    key = (cx << 32) ^ (cy & 0xFFFFFFFF)
    order = np.lexsort((off_centre, key))  # by voxel, nearest the centre first in each ...
    sorted_key = key[order]
    first = np.concatenate(([True], sorted_key[1:] != sorted_key[:-1]))  # ... so the first of a voxel wins
    return np.sort(order[first])


def _nearest_centre_dense(voxel: np.ndarray, voxels: int, off_centre: np.ndarray) -> np.ndarray:
    """Per voxel index (0 <= voxel < voxels), the first of its points with the least ``off_centre``.

    Only the voxels that hold a point are ever read, so only they are given a start value
    (a submap's box is ~20 voxels a point: filling all of them was most of the cost).
    """
    nearest = np.empty(voxels)
    nearest[voxel] = np.inf
    np.minimum.at(nearest, voxel, off_centre)
    tied = np.flatnonzero(off_centre == nearest[voxel])  # ascending: the first of a tie comes first
    tied_voxel = voxel[tied]
    first = np.empty(voxels, dtype=np.int64)
    first[tied_voxel] = off_centre.size
    np.minimum.at(first, tied_voxel, tied)
    return tied[first[tied_voxel] == tied]


def prepare_scan(scan: Scan, pose_at_time: PoseAtTime | None, params: PrepareParams | None = None) -> PreparedScan:
    """Filter, de-skew and downsample one revolution (see the module docstring).

    ``pose_at_time`` gives the odometry pose at any sample time; ``None`` assumes the
    robot stood still (no de-skew), e.g. for logs without per-sample timing.
    """
    p = params or PrepareParams()
    angle = np.asarray(scan.angle_rad, dtype=np.float64)
    rng = np.asarray(scan.range_m, dtype=np.float64)
    time = np.asarray(scan.time_s, dtype=np.float64)
    end_time_s = scan.end_time_s

    # 1. range gate: hits in [min, max]; valid returns beyond max are no-return beams
    usable = np.asarray(scan.valid, dtype=bool) & np.isfinite(rng) & (rng >= p.min_range_m)
    in_range = usable & (rng <= p.max_range_m)
    no_return = usable & (rng > p.max_range_m)

    # 2. impulse rejection along the in-range samples, in scan order
    idx = np.flatnonzero(in_range)
    keep = impulse_mask(rng[idx], p.median_window, p.impulse_abs_m, p.impulse_rel, p.circular)
    rejected = int(idx.size - np.count_nonzero(keep))
    idx = idx[keep]
    free_idx = np.flatnonzero(no_return)

    # 3. de-skew hits and no-return beams into the end pose's robot frame
    points, origins = _deskew(angle[idx], rng[idx], time[idx], end_time_s, pose_at_time, p)
    free_points, free_origins = _deskew(
        angle[free_idx], np.full(free_idx.size, p.max_range_m), time[free_idx], end_time_s, pose_at_time, p
    )

    # 4. downsample for matching; the full set stays for the map
    match = points[voxel_downsample(points, p.voxel_size_m)]
    return PreparedScan(
        points_full=points,
        points_match=match,
        origins_full=origins,
        free_endpoints=free_points,
        free_origins=free_origins,
        angle_rad=angle[idx],
        range_m=rng[idx],
        time_s=end_time_s,
        sensor_xy=np.array([p.mount_x_m, p.mount_y_m]),
        index=idx,
        sensor_yaw_rad=p.mount_yaw_rad,
        rejected_impulses=rejected,
    )


def _deskew(
    angle_rad: np.ndarray,
    range_m: np.ndarray,
    time_s: np.ndarray,
    end_time_s: float,
    pose_at_time: PoseAtTime | None,
    p: PrepareParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Points and lidar origins (N, 2) in the robot frame at ``end_time_s``.

    ``p_end = T_end⁻¹ ∘ T(t_i) ∘ T_mount ∘ p_lidar``, all samples at once.
    """
    # lidar frame -> robot frame at the sample's own time (mounting offset)
    a = angle_rad + p.mount_yaw_rad
    x = p.mount_x_m + range_m * np.cos(a)
    y = p.mount_y_m + range_m * np.sin(a)
    ox = np.full_like(x, p.mount_x_m)
    oy = np.full_like(y, p.mount_y_m)
    if pose_at_time is not None and angle_rad.size:
        xs, ys, ths = (np.asarray(v, dtype=np.float64) for v in pose_at_time(time_s))
        xe, ye, the = (float(np.asarray(v).reshape(-1)[0]) for v in pose_at_time(np.array([end_time_s])))
        # relative transform T_end⁻¹ ∘ T(t_i): rotation th_i - th_end, translation R(-th_end)(t_i - t_end)
        ce, se = np.cos(the), np.sin(the)
        dx, dy = xs - xe, ys - ye
        rel_x, rel_y = ce * dx + se * dy, -se * dx + ce * dy
        dth = ths - the
        c, s = np.cos(dth), np.sin(dth)
        x, y = c * x - s * y + rel_x, s * x + c * y + rel_y
        ox, oy = c * ox - s * oy + rel_x, s * ox + c * oy + rel_y
    return np.column_stack((x, y)), np.column_stack((ox, oy))
