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

#: A face seen at rest may run over two or three boards in line, each set at its own offset
#: (σ 4 mm) and thickness (6-20 mm): the face steps across by a few millimetres where they
#: meet, too little to split it (``FACE_GAP_ACROSS_M``), and one least-squares line through
#: the step reads it as a turn of up to 2° (the bench's hand-built 8×8 seed 6: two boards
#: turned +0.21° and -0.75° read -2.18°). With ``steps`` a face's direction is the common
#: slope of its pieces, each with an offset of its own (an analysis of covariance: the slope
#: within the pieces, Scheffé 1959, ch. 6), cut where the step between the pieces is at least
#: ``FACE_STEP_MIN_M`` and ``FACE_STEP_SIGNIFICANCE`` of its standard errors ...
FACE_STEP_MIN_M = 0.003
FACE_STEP_SIGNIFICANCE = 5.0

#: ... each piece at least this long (a board is 0.28 m; a shorter piece is a post's end) ...
FACE_PIECE_MIN_M = 0.08

#: ... and at most this many cuts (a face of three boards in line; the longest faces seen at rest).
FACE_MAX_STEPS = 2

#: Cut positions tried per piece: evenly spread over the piece's points (the step sits within a
#: post's width, 12 mm, of the best of them; the common slope moves little across that).
FACE_CUTS_TRIED = 60

#: A face's points near its ends are smoothed (``[slam.normals] smooth``) onto lines through
#: neighbours that reach past the end, onto a post's side or across the gap to the next
#: board: about half the ``neighbours`` beams, 5 at the A1's 1° spacing, 13 mm at 0.15 m and
#: 40 mm at 0.45 m. At rest 20 revolutions average the lidar's noise away, not that bend: a
#: face of one board 0.45 m from the start of the bench's hand-built 8×8 seed 8 read +0.46°
#: where its board stands at -0.11°, and -0.03° without 4 cm at each end.
#: ``wall_faces(end_trim_m=...)`` reads a face's direction without them (``[slam.walls]
#: rest_face_end_trim_m``, the faces seen at rest).


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


def wall_faces(
    points: np.ndarray, normals: np.ndarray, grid_rad: float, steps: bool = False, end_trim_m: float = 0.0
) -> Faces:
    """The straight faces among surface points of one place (module docstring), in their frame.

    ``points`` (N, 2) and ``normals`` (N, 2) are a place's surface points (a keyframe's
    frame); ``grid_rad`` the wall grid's direction in that frame (modulo 90°), which sorts
    the points by the axis their normals face. A face's own direction is its least-squares
    line's; only faces that pass the module's tests are kept. With ``steps`` (the faces seen
    at rest, many revolutions pooled) a face's direction is taken across the steps between
    boards in line (:func:`slope_across_steps`); which faces are kept does not change.
    With ``end_trim_m`` > 0 a face's direction is read without its points within that of
    either end (:func:`_inner`); which faces are kept, their centres and lengths do not change.
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
                if end_trim_m > 0.0:
                    a, b, slope = _inner(a, b, slope, end_trim_m)
                if steps:
                    slope = slope_across_steps(a, b, slope)
                centre = (mid_across, mid_along) if axis == 0 else (mid_along, mid_across)
                rows.append((*centre, nominal + sign * math.atan(slope), 0.5 * float(b[-1] - b[0]), a.size))
    if not rows:
        return NO_FACES
    table = np.array(rows)
    gu, gv = table[:, 0], table[:, 1]
    centre_xy = np.column_stack((c * gu - s * gv, s * gu + c * gv))
    return Faces(centre_xy, table[:, 2] + grid_rad, table[:, 3], table[:, 4].astype(np.intp))


def _inner(across: np.ndarray, along: np.ndarray, slope: float, trim_m: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A face's points (sorted by ``along``) without those within ``trim_m`` of either end, and their slope.

    The face as it is (``slope`` its whole line's) where what is left is shorter than
    ``FACE_PIECE_MIN_M``, has fewer than ``FACE_MIN_POINTS`` or too large a standard error.
    """
    inner = (along >= along[0] + trim_m) & (along <= along[-1] - trim_m)
    a, b = across[inner], along[inner]
    if a.size < FACE_MIN_POINTS or b[-1] - b[0] < FACE_PIECE_MIN_M:
        return across, along, slope
    fitted = _slope(a, b)
    if fitted is None:
        return across, along, slope
    return a, b, fitted[0]


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


def slope_across_steps(across: np.ndarray, along: np.ndarray, one_line: float) -> float:
    """The slope of ``across`` against ``along`` (sorted by ``along``) common to the boards in line a face runs over.

    A piece of the face is one board, offset from its neighbours by a step: cut greedily where
    the common slope with an offset per piece (:func:`_common_slope`) leaves the least squared
    residual, each cut kept only if its step is at least ``FACE_STEP_MIN_M`` and
    ``FACE_STEP_SIGNIFICANCE`` of its standard errors (a face of one board keeps its one line:
    the lidar's noise does not pose as a step), at most ``FACE_MAX_STEPS`` cuts. The slope
    within pieces is unbiased with or without a step; cut where there is none, it only loses
    a little precision.

    Where no cut holds the face is one line, and its least-squares slope ``one_line``
    (:func:`_slope`'s) is returned as it is. The one piece's common slope is the same fit
    summed in another order (its means by ``np.bincount``, not ``mean``'s pairwise sum) and
    may differ in the last bits; it could move a face of a maze built exactly by a unit in
    the last place of its normal, and a run would then part from the run with one line.
    """
    piece = np.zeros(across.size, dtype=np.intp)
    for _ in range(FACE_MAX_STEPS):
        cut = _best_cut(across, along, piece)
        if cut is None or not _step_holds(across, along, piece, cut):
            break
        piece = _cut_at(piece, cut)
    if not piece.any():
        return one_line
    return _common_slope(across, along, piece)[0]


def _common_slope(across: np.ndarray, along: np.ndarray, piece: np.ndarray) -> tuple[float, np.ndarray]:
    """The slope common to every piece, each with an offset of its own, and the residuals (ANCOVA)."""
    count = np.bincount(piece)
    mean_along = (np.bincount(piece, weights=along) / count)[piece]
    mean_across = (np.bincount(piece, weights=across) / count)[piece]
    centred_along, centred_across = along - mean_along, across - mean_across
    slope = float(centred_along @ centred_across) / float(centred_along @ centred_along)
    return slope, centred_across - slope * centred_along


def _best_cut(across: np.ndarray, along: np.ndarray, piece: np.ndarray) -> int | None:
    """The index (points sorted by ``along``) where one more cut leaves the least squared residual, or None."""
    best: tuple[float, int] | None = None
    for label in range(int(piece.max()) + 1):
        members = np.flatnonzero(piece == label)
        first = int(np.searchsorted(along[members], along[members[0]] + FACE_PIECE_MIN_M))
        end = int(np.searchsorted(along[members], along[members[-1]] - FACE_PIECE_MIN_M))
        for k in range(first, end, max(1, (end - first) // FACE_CUTS_TRIED)):
            _, residual = _common_slope(across, along, _cut_at(piece, int(members[k])))
            squared = float(residual @ residual)
            if best is None or squared < best[0]:
                best = (squared, int(members[k]))
    return None if best is None else best[1]


def _cut_at(piece: np.ndarray, index: int) -> np.ndarray:
    """``piece`` with the points of ``index``'s piece from ``index`` on made a piece of their own."""
    cut = piece.copy()
    tail = (np.arange(piece.size) >= index) & (piece == piece[index])
    cut[tail] = piece.max() + 1
    return cut


def _step_holds(across: np.ndarray, along: np.ndarray, piece: np.ndarray, index: int) -> bool:
    """Whether the step between the two pieces a cut at ``index`` makes is large and significant.

    The step is the two pieces' lines' difference at the cut, along the common slope; its
    standard error that of two fitted lines' values there (the residuals' scatter).
    """
    cut = _cut_at(piece, index)
    slope, residual = _common_slope(across, along, cut)
    sigma2 = float(residual @ residual) / max(1, across.size - int(cut.max()) - 2)
    at_m = 0.5 * float(along[index - 1] + along[index])
    values, variance = [], 0.0
    for label in (piece[index], cut[index]):
        members = cut == label
        mean_along = float(along[members].mean())
        spread = float(np.sum((along[members] - mean_along) ** 2))
        values.append(float(across[members].mean()) + slope * (at_m - mean_along))
        variance += sigma2 * (1.0 / members.sum() + (at_m - mean_along) ** 2 / max(spread, 1e-12))
    step_m = abs(values[1] - values[0])
    return step_m >= FACE_STEP_MIN_M and step_m >= FACE_STEP_SIGNIFICANCE * math.sqrt(variance)


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
