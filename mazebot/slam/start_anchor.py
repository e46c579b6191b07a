"""The maze's wall grid as seen from the start of a maze built by hand: every board judged together.

Keyframe 0, the map's anchor, measures the walls it sees while the robot stands still
(:mod:`mazebot.slam.wall_priors`). In a maze built by hand each board stands at its own
small angle (a few tenths of a degree), so the two to four faces seen from the start are
not the maze's grid: anchored to their mean, the whole map turns about the start by their
error; not anchored at all, it keeps whatever turn the first in-place turns left in the
chain of scan matches (:mod:`mazebot.slam.wall_faces` tells the two kinds of maze apart).

Two directions, each measured without the boards' turns, mend both:

1. the **maze's grid in the map**, ``G``: the median of the directions of every face every
   keyframe saw, placed in the map, each stretch of wall counted once however often the
   robot saw it (about a hundred boards at 0.7° each: a few hundredths of a degree off the
   maze's mean); the Manhattan-world direction of all the walls (Coughlan & Yuille,
   "Manhattan World", ICCV 1999);
2. the **map's turn at the start**, ``δ``: the faces keyframe 0 measured at rest, against
   the same stretches of the same faces as the other keyframes near the start drew them in
   the map. Both are fitted over the same 2 cm bins along each face, so a face that runs
   over two boards in line is the same mixture of them on both sides, and the difference
   of the two slopes is the map's turn there, not a board's. The faces are weighted by the
   inverse variance of that difference (a far or short face says less).

The grid in keyframe 0's frame is then ``G − δ`` (less keyframe 0's heading): a map turned
as a whole by the first turns' error shows it in ``δ`` and ``G`` alike, so it cancels, and
the boards keyframe 0 happened to see weigh no more than any others. ``None`` until a
keyframe near the start has seen one of keyframe 0's faces.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mazebot.geometry import relative_pose, transform_points
from mazebot.slam.keyframes import Keyframe
from mazebot.slam.wall_faces import AXIS_TOLERANCE_RAD, Faces, quarter_turns, wall_faces

#: The start's surface at rest is kept as the mean point of each square of this side: the
#: 20 revolutions' points (some 6 000) become a few hundred, well below the 2 cm bins.
REST_VOXEL_M = 0.01

#: A point lies on one of keyframe 0's faces if it lies within this across its line: the map's
#: turn at the start (under a degree: 5 mm over 0.3 m) and a board's thickness (the other face,
#: 6-20 mm away, faces the other way and is left out by its normal).
FACE_BAND_M = 0.02

#: Points are compared along a face in bins of this length (the A1's samples on a wall 0.3 m
#: away lie ~5 mm apart: several per bin).
BIN_M = 0.02

#: A face's turn in the map is measured over at least this many bins both sides share (10 cm).
MIN_SHARED_BINS = 5

#: A face's turn counts at most as if its slopes' variance were this ((0.02°)²): a face fitted
#: exactly (a simulated lidar without noise) does not drown the others.
MIN_SLOPE_VAR = math.radians(0.02) ** 2

#: ``G`` counts each stretch of wall once: faces on one side within this across ...
STRETCH_ACROSS_M = 0.05

#: ... and this along (a cell) are one stretch.
STRETCH_ALONG_M = 0.3

#: Keyframes whose lidar stood within this of keyframe 0's in the map measure the map's turn at
#: the start: they see its faces from near by, where the chain's turn is what the map shows.
START_REACH_M = 1.0


@dataclass(frozen=True)
class RestSurface:
    """Keyframe 0's faces at rest and its surface averaged per ``REST_VOXEL_M`` square (its frame)."""

    faces: Faces
    points: np.ndarray
    normals: np.ndarray

    @staticmethod
    def measured(points: np.ndarray, normals: np.ndarray, grid_rad: float) -> RestSurface:
        """From the revolutions' surfaces pooled (``points``, ``normals`` (N, 2)); ``grid_rad`` sorts the faces."""
        faces = wall_faces(points, normals, grid_rad)
        keys = np.floor(np.asarray(points) / REST_VOXEL_M).astype(np.int64)
        _, voxel, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        voxel = voxel.reshape(-1)
        mean_points = np.column_stack([np.bincount(voxel, points[:, d]) for d in range(2)]) / counts[:, None]
        summed = np.column_stack([np.bincount(voxel, normals[:, d]) for d in range(2)])
        mean_normals = summed / np.maximum(np.hypot(summed[:, 0], summed[:, 1]), 1e-12)[:, None]
        return RestSurface(faces, mean_points, mean_normals)


def start_anchor_rad(
    rest: RestSurface, keyframes: Sequence[Keyframe], poses: np.ndarray, reference_rad: float
) -> float | None:
    """Keyframe 0's anchor direction in its own frame (modulo 90°): ``G − δ`` of the module docstring.

    ``poses`` (K, 3) are the keyframes' current poses, ``reference_rad`` the wall grid's
    direction in the map as known so far (it sorts the faces by their side). Every keyframe
    after the first adds its faces (:meth:`mazebot.slam.keyframes.Keyframe.wall_faces`,
    cached) to ``G``; those within ``START_REACH_M`` of keyframe 0 their surfaces to ``δ``.
    """
    if len(keyframes) < 2 or not len(rest.faces):
        return None
    seen = Faces.joined([keyframes[k].wall_faces().placed(poses[k]) for k in range(1, len(keyframes))])
    if not len(seen):
        return None
    grid_rad = reference_rad + grid_turn_rad(seen, reference_rad)
    turn = start_turn_rad(rest, keyframes, poses)
    if turn is None:
        return None
    return float(quarter_turns(np.array([grid_rad - turn - float(poses[0, 2])]))[0])


def grid_turn_rad(faces: Faces, reference_rad: float) -> float:
    """``G`` less ``reference_rad``: the median over stretches of wall of each stretch's median face turn.

    A stretch is a side (the way its normal faces), ``STRETCH_ACROSS_M`` across and
    ``STRETCH_ALONG_M`` along on the grid's axes: a place the robot lingered at (the start's
    in-place turns, a corridor driven twice) counts once.
    """
    relative = faces.normal_rad - reference_rad
    turns = quarter_turns(relative)
    side = np.round((relative - turns) / (math.pi / 2)).astype(np.int64) % 4
    c, s = math.cos(reference_rad), math.sin(reference_rad)
    u = c * faces.centre_xy[:, 0] + s * faces.centre_xy[:, 1]
    v = -s * faces.centre_xy[:, 0] + c * faces.centre_xy[:, 1]
    across_u = side % 2 == 0
    across = np.floor(np.where(across_u, u, v) / STRETCH_ACROSS_M).astype(np.int64)
    along = np.floor(np.where(across_u, v, u) / STRETCH_ALONG_M).astype(np.int64)
    _, stretch = np.unique(np.column_stack((side, across, along)), axis=0, return_inverse=True)
    stretch = stretch.reshape(-1)
    medians = [float(np.median(turns[stretch == k])) for k in range(int(stretch.max()) + 1)]
    return float(np.median(medians))


def start_turn_rad(rest: RestSurface, keyframes: Sequence[Keyframe], poses: np.ndarray) -> float | None:
    """``δ``: how far the map turns keyframe 0's faces as the keyframes near it drew them (radians, CCW).

    Everything in keyframe 0's frame; each face's turn weighted by the bins both sides share.
    None if no face has ``MIN_SHARED_BINS`` of them.
    """
    start_lidar = transform_points(poses[0], keyframes[0].sensor_xy[None, :])[0]
    near = [k for k in range(1, len(keyframes))
            if math.dist(transform_points(poses[k], keyframes[k].sensor_xy[None, :])[0], start_lidar) <= START_REACH_M]
    if not near:
        return None
    points, normals = [], []
    for k in near:  # their surfaces in keyframe 0's frame
        pts, nrm = keyframes[k].surface()
        rel = relative_pose(poses[0], poses[k])
        points.append(transform_points(rel, pts))
        normals.append(transform_points((0.0, 0.0, rel[2]), nrm))
    seen_points, seen_normals = np.concatenate(points), np.concatenate(normals)
    turns, weights = [], []
    for i in range(len(rest.faces)):
        mine = _face_profile(rest.faces, i, rest.points, rest.normals)
        theirs = _face_profile(rest.faces, i, seen_points, seen_normals)
        shared = np.intersect1d(mine[0], theirs[0])
        if shared.size < MIN_SHARED_BINS:
            continue
        along = (shared + 0.5) * BIN_M
        slope_mine, var_mine = _slope(along, mine[1][np.searchsorted(mine[0], shared)])
        slope_theirs, var_theirs = _slope(along, theirs[1][np.searchsorted(theirs[0], shared)])
        # the face's points turned by +t (counter-clockwise) lie across it at -tan(t) times along
        turns.append(math.atan(slope_mine) - math.atan(slope_theirs))
        weights.append(1.0 / max(var_mine + var_theirs, MIN_SLOPE_VAR))
    if not turns:
        return None
    return float(np.average(turns, weights=weights))


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value at which the weights below and above balance (the lower one at a tie)."""
    order = np.argsort(values)
    cumulative = np.cumsum(np.asarray(weights, dtype=np.float64)[order])
    return float(np.asarray(values)[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def _face_profile(faces: Faces, i: int, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points on face ``i``: their bins along it (sorted, unique) and each bin's mean offset across it."""
    angle = float(faces.normal_rad[i])
    n = np.array([math.cos(angle), math.sin(angle)])
    t = np.array([-n[1], n[0]])
    rel = points - faces.centre_xy[i]
    across, along = rel @ n, rel @ t
    keep = (
        (np.abs(across) <= FACE_BAND_M)
        & (np.abs(along) <= faces.half_length_m[i])
        & (normals @ n >= math.cos(AXIS_TOLERANCE_RAD))
    )
    bins = np.floor(along[keep] / BIN_M).astype(np.int64)
    unique, inverse, counts = np.unique(bins, return_inverse=True, return_counts=True)
    return unique, np.bincount(inverse.reshape(-1), across[keep]) / counts


def _slope(along: np.ndarray, across: np.ndarray) -> tuple[float, float]:
    """The least-squares slope of ``across`` against ``along``, and its variance."""
    centred = along - along.mean()
    spread = float(centred @ centred)
    slope = float(centred @ (across - across.mean())) / spread
    residual = across - across.mean() - slope * centred
    return slope, float(residual @ residual) / max(1, along.size - 2) / spread
