"""Each wall face's own direction, and how far the faces seen from one place turn apart.

The map's anchor (:mod:`mazebot.slam.wall_priors`) ties the wall grid's direction to the
walls keyframe 0 sees at the start. That holds where every wall lies on one grid (a maze
cut by machine): the faces seen from the start then run in one direction, to the
lidar's noise. In a maze built by hand each board is set at its own small angle (a few
tenths of a degree), and the mean direction of the two to four faces seen from the start
is off the maze's mean grid by about as much: tied to it, the whole map turns about the
start by that error (0.6° on a 6×6 maze measured: 2 cm at its far side, a one-cell band
of cells beside every wall painted occupied).

So the faces seen at rest are measured one by one: surface points split by the grid
axis their normal faces, then into faces by gaps across and along; each long enough face
gets its own direction by least squares (the line's slope against the grid axis), kept
only if its standard error is small, so that the lidar's noise over a short stretch does
not pose as a turned board. The spread of those directions about their mean says whether
the faces lie on one grid (:func:`face_spread`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

#: A point belongs to a grid axis's faces if its normal lies within this of the axis
#: (the smoothed normals of a face scatter by a few degrees; a post's round side does not
#: stay within it for long).
AXIS_TOLERANCE_RAD = math.radians(15.0)

#: Points of one axis more than this apart across the face (after sorting) lie on different
#: faces: two parallel boards are at least a wall's thickness (6 mm) apart, one board's face
#: spreads by the A1's range noise (~1 % of 0.1-0.5 m, smoothed onto local lines).
FACE_GAP_ACROSS_M = 0.004

#: ... and points of one face more than this apart along it are two faces (a gap at a post,
#: a shadow): each is its own board.
FACE_GAP_ALONG_M = 0.05

#: A face needs this many points ...
FACE_MIN_POINTS = 20

#: ... over at least this length: a near wall that the lidar's 0.15 m minimum range splits
#: into two short halves shows each half turned by up to ±0.5° from the ends' smoothing.
FACE_MIN_LENGTH_M = 0.12

#: A face's direction counts only if its least-squares standard error is within this
#: (0.1°): below the boards' turns of a hand-built maze, above the A1's noise over a
#: well-seen face.
FACE_MAX_STDERR_RAD = math.radians(0.1)


@dataclass(frozen=True)
class Faces:
    """Straight wall faces of one place, each a segment with its outward normal (the frame of its points).

    ``centre_xy`` (F, 2) the middle of the points' fitted line, ``normal_rad`` (F,) the
    normal's direction (pointing to the side the lidar saw the face from), ``half_length_m``
    (F,) half the points' extent along the face, ``count`` (F,) its points.
    """

    centre_xy: np.ndarray
    normal_rad: np.ndarray
    half_length_m: np.ndarray
    count: np.ndarray

    def __len__(self) -> int:
        return int(self.count.size)

    def placed(self, pose: np.ndarray) -> Faces:
        """The same faces in the frame where ``pose`` (3,) is their frame's pose."""
        c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
        x, y = self.centre_xy[:, 0], self.centre_xy[:, 1]
        centre = np.column_stack((pose[0] + c * x - s * y, pose[1] + s * x + c * y))
        return Faces(centre, self.normal_rad + float(pose[2]), self.half_length_m, self.count)

    @staticmethod
    def joined(parts: list[Faces]) -> Faces:
        """All faces of ``parts`` in one."""
        if not parts:
            return NO_FACES
        return Faces(*(np.concatenate([getattr(f, name) for f in parts]) for name in Faces.__dataclass_fields__))


NO_FACES = Faces(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.intp))


def wall_faces(points: np.ndarray, normals: np.ndarray, grid_rad: float) -> Faces:
    """The straight faces among surface points of one place (module docstring), in their frame.

    ``points`` (N, 2) and ``normals`` (N, 2) are a place's surface points (a keyframe's
    frame); ``grid_rad`` the wall grid's direction in that frame (modulo 90°), which sorts
    the points by the axis their normals face. A face's own direction is its least-squares
    line's; only faces that pass the module's tests are kept.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    c, s = math.cos(grid_rad), math.sin(grid_rad)
    u = c * pts[:, 0] + s * pts[:, 1]
    v = -s * pts[:, 0] + c * pts[:, 1]
    nu = c * nrm[:, 0] + s * nrm[:, 1]
    nv = -s * nrm[:, 0] + c * nrm[:, 1]
    cos_tol = math.cos(AXIS_TOLERANCE_RAD)
    rows: list[tuple[float, float, float, float, int]] = []  # (u, v, normal on the grid, half length, points)
    # faces across u (normal along ±u: the line runs along v) and across v (the line runs along u);
    # a line u = a + b v is the v axis turned by -atan(b), a line v = a + b u the u axis turned by +atan(b)
    for across, along, normal, sign, axis in ((u, v, nu, -1.0, 0), (v, u, nv, 1.0, 1)):
        for side in (1.0, -1.0):
            keep = side * normal >= cos_tol
            nominal = axis * math.pi / 2 + (0.0 if side > 0 else math.pi)  # the normal's angle on the grid
            for a, b in _faces(across[keep], along[keep]):
                fitted = _slope(a, b)
                if fitted is None:
                    continue
                slope, mid_across, mid_along = fitted
                centre = (mid_across, mid_along) if axis == 0 else (mid_along, mid_across)
                rows.append((*centre, nominal + sign * math.atan(slope), 0.5 * float(b[-1] - b[0]), a.size))
    if not rows:
        return NO_FACES
    table = np.array(rows)
    gu, gv = table[:, 0], table[:, 1]
    centre_xy = np.column_stack((c * gu - s * gv, s * gu + c * gv))
    return Faces(centre_xy, table[:, 2] + grid_rad, table[:, 3], table[:, 4].astype(np.intp))


def face_turns(points: np.ndarray, normals: np.ndarray, grid_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Each face's turn from the grid direction ``grid_rad`` (radians, counter-clockwise) and its point count.

    ``points`` (N, 2) and ``normals`` (N, 2) are surface points of one place (a keyframe's
    frame); ``grid_rad`` the wall grid's direction in that frame (modulo 90°). Returns
    ``(turns_rad (F,), points (F,))`` for the faces of :func:`wall_faces`.
    """
    faces = wall_faces(points, normals, grid_rad)
    return quarter_turns(faces.normal_rad - grid_rad), faces.count


def quarter_turns(angles_rad: np.ndarray) -> np.ndarray:
    """Angles modulo 90°, in [-45°, 45°)."""
    return np.remainder(np.asarray(angles_rad, dtype=np.float64) + math.pi / 4, math.pi / 2) - math.pi / 4


def face_spread(turns_rad: np.ndarray, counts: np.ndarray) -> float | None:
    """The faces' turns' RMS about their mean, weighted by points (radians); None below two faces."""
    turns = np.asarray(turns_rad, dtype=np.float64)
    if turns.size < 2:
        return None
    weights = np.asarray(counts, dtype=np.float64)
    mean = float(np.average(turns, weights=weights))
    return math.sqrt(float(np.average((turns - mean) ** 2, weights=weights)))


def _faces(across: np.ndarray, along: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """The points of one axis and side split into faces: by gaps across, then by gaps along.

    A face is a run of one part's points, so a part of fewer than ``FACE_MIN_POINTS`` holds
    none and is passed over unsorted: most parts are a point or two (a post's round side,
    noise between two boards), and sorting each cost a dozen numpy calls for nothing.
    """
    faces = []
    order = np.argsort(across)
    across, along = across[order], along[order]
    for lo, hi in _runs(np.diff(across) > FACE_GAP_ACROSS_M):
        if hi - lo < FACE_MIN_POINTS:
            continue
        a, b = across[lo:hi], along[lo:hi]
        by_along = np.argsort(b)
        a, b = a[by_along], b[by_along]
        for first, end in _runs(np.diff(b) > FACE_GAP_ALONG_M):
            if end - first >= FACE_MIN_POINTS and b[end - 1] - b[first] >= FACE_MIN_LENGTH_M:
                faces.append((a[first:end].copy(), b[first:end].copy()))
    return faces


def _runs(gap_after: np.ndarray) -> list[tuple[int, int]]:
    """``[first, end)`` of each run of points between the gaps, where ``gap_after`` (N - 1,) marks a gap
    after each point: the parts ``np.split`` would cut at ``flatnonzero(gap_after) + 1``."""
    cuts = [0, *(np.flatnonzero(gap_after) + 1).tolist(), gap_after.size + 1]
    return list(itertools.pairwise(cuts))


def _slope(across: np.ndarray, along: np.ndarray) -> tuple[float, float, float] | None:
    """The slope of ``across`` against ``along`` by least squares and the two means, or None if its
    standard error is too large. Each mean is taken once: the fit and the face's centre share them."""
    mean_along = along.mean()
    mean_across = across.mean()
    centred = along - mean_along
    spread = float(centred @ centred)
    across_centred = across - mean_across
    slope = float(centred @ across_centred) / spread
    residual = across_centred - slope * centred
    stderr = math.sqrt(float(residual @ residual) / max(1, across.size - 2) / spread)
    if math.atan(stderr) > FACE_MAX_STDERR_RAD:
        return None
    return slope, float(mean_across), float(mean_along)
