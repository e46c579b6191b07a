"""The maze's walls as priors of the pose graph: one direction for every wall, and the lattice they stand on.

In a maze every wall lies on one right-angle grid whose direction ``φ`` (map frame,
modulo 90°) is unknown. A keyframe at heading ``θ_k`` whose walls lie at ``d_k`` in its
own frame says ``θ_k + d_k ≡ φ (mod 90°)``. ``φ`` is an extra vertex of the graph (its
heading; its position is pinned to keyframe 0's), and every keyframe whose walls show
the grid gets a heading-only edge ``φ → k`` measuring ``θ_k − φ`` (the multiple of 90°
nearest the current estimate). So ``φ`` is estimated from all keyframes together with
the poses, instead of being taken from one keyframe's noisy wall direction: a reference
off by 0.15° rotates the whole map by 0.15°, 1.2 cm at the far side of a 16×16 maze. The
chain of scan matches keeps its local shape; these edges, each weak, keep its heading
from drifting over hundreds of metres (the Manhattan-world constraint of Peasley,
Birchfield, Cunningham & Fiedler, "Accurate on-line 3D occupancy grids using Manhattan
world constraints", IROS 2012, with the direction estimated rather than assumed).

Estimated from the keyframes alone, ``φ`` follows the map wherever its chain of matches
turned it: the first in-place turns, matched against a submap of one or two keyframes,
leave the whole map turned by a few tenths of a degree about the start, and every later
keyframe agrees with that. Keyframe 0, the **anchor**, is the map frame's origin by
definition and measured its walls while the robot stood still (``anchor_wall``: the mean
of many revolutions' wall directions, several times less noisy than one scan's): its
tight edge ties ``φ`` to the walls as seen from the start, and the other keyframes'
priors turn the map back onto them.

With a lattice (:mod:`mazebot.slam.wall_lattice`) the same keyframes' wall faces also tie
their positions to the maze's lattice (:func:`lattice_edges`); the vertex then stands
where the lattice's lines cross, and its position is estimated too.

The loop-closure job (:class:`mazebot.slam.slam.LoopClosureJob`) adds these to the graph
it optimizes; they are functions of the keyframes and their poses only.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mazebot.geometry import relative_pose, wrap_angle
from mazebot.slam.keyframes import Keyframe
from mazebot.slam.lattice_fit import PitchFit, fit_pitch
from mazebot.slam.wall_lattice import LatticeParams, lattice_priors
from mazebot.slam_config import WallSection

#: At most about this many keyframes, evenly spread, measure the lattice's pitch (the walls
#: repeat from keyframe to keyframe; more only costs time in every optimization).
LATTICE_FIT_KEYFRAMES = 200

#: A loop-closure job fits the lattice again only once the keyframes have grown by this factor
#: since the fit it was given (:class:`mazebot.slam.slam.LoopClosureJob`). The pitch and the
#: lines' phases are properties of the maze, measured over up to ``LATTICE_FIT_KEYFRAMES`` of
#: them: a job three keyframes after the last sees the same walls, and the fit (12-15 ms of a
#: 6x6 exploration's 40-60 ms jobs) came out the same to the tenth of a millimetre the lattice
#: priors round the pitch to. A quarter more keyframes is new ground worth a new look.
LATTICE_REFIT_GROWTH = 1.25


def wrap_quarter(angle_rad: float) -> float:
    """An angle modulo 90°, in [-45°, 45°)."""
    return (angle_rad + math.pi / 4) % (math.pi / 2) - math.pi / 4


@dataclass(frozen=True)
class WallPriors:
    """The wall vertex and its edges, ready to join a pose graph of ``K`` keyframes as vertex ``K``.

    ``vertex`` (1, 3) is the wall grid's pose (heading ``φ``; position keyframe 0's, or a
    crossing of the lattice's lines); ``i``, ``j`` (E,), ``z`` (E, 3) and ``information``
    (E, 3, 3) are edges in the pose graph's arrays.
    """

    vertex: np.ndarray
    i: np.ndarray
    j: np.ndarray
    z: np.ndarray
    information: np.ndarray


def wall_priors(
    keyframes: Sequence[Keyframe],
    poses: np.ndarray,
    reference_rad: float | None,
    walls: WallSection,
    lattice: LatticeParams | None,
    anchor_wall: tuple[float, float] | None = None,
    known_fit: PitchFit | None = None,
) -> tuple[WallPriors | None, PitchFit | None]:
    """The wall-direction vertex and its edges (module docstring), and the lattice fit if one was made.

    ``poses`` (K, 3) are the keyframes' current poses, ``reference_rad`` the wall grid's
    direction as known so far (None: not yet: no priors), ``anchor_wall`` keyframe 0's
    wall direction in its own frame and its std (None: keyframe 0 is no anchor),
    ``known_fit`` a lattice fitted before to take instead of fitting it again (None: fit it;
    see ``LATTICE_REFIT_GROWTH``); it is returned as the fit.
    """
    if not walls.wall_prior or reference_rad is None or len(keyframes) < 2:
        return None, None
    reference = float(reference_rad)
    rows = []
    first = 0 if anchor_wall is not None else 1  # keyframe 0 is fixed: as one of many it means little
    for k in range(first, len(keyframes)):
        if k == 0 and anchor_wall is not None:
            direction, std = anchor_wall
        else:
            direction, strength, count = keyframes[k].wall_direction()
            if strength < walls.wall_min_strength or count < walls.wall_min_normals:
                continue
            if walls.wall_prior_faces:
                by_faces = keyframes[k].face_wall_direction()
                direction = direction if by_faces is None else by_faces
            std = walls.wall_prior_std_rad
        theta = float(poses[k, 2])
        deviation = wrap_quarter(direction + theta - reference)
        if abs(deviation) <= walls.wall_max_deviation_rad:
            rows.append((k, theta - reference - deviation, std))
    if not rows:
        return None, None
    wall = poses.shape[0]  # the index the wall vertex gets
    wall_pose = np.array([[poses[0, 0], poses[0, 1], reference]])
    index = np.array([k for k, _, _ in rows])
    z = relative_pose(wall_pose[0], poses[index])
    z[:, 2] = wrap_angle(np.array([t for _, t, _ in rows]))
    info = np.zeros((len(rows) + 1, 3, 3))
    info[:-1, 2, 2] = 1.0 / np.array([std for _, _, std in rows]) ** 2
    info[-1, 0, 0] = info[-1, 1, 1] = 1e6  # the vertex's position sits on keyframe 0 (it means nothing)
    ei = np.concatenate((np.full(len(rows), wall, dtype=np.intp), [0]))
    ej = np.concatenate((index, [wall])).astype(np.intp)
    z = np.vstack((z, relative_pose(poses[0], wall_pose[0])))
    fit = None
    if lattice is not None:
        fit = known_fit if known_fit is not None else lattice_fit(keyframes, poses, index, reference, lattice)
        edges = lattice_edges(keyframes, poses, index, reference, lattice, fit)
        if edges is not None:
            wall_pose[0, :2], lattice_j, lattice_z, lattice_info = edges
            # the vertex's position, where the lattice's lines cross, is estimated with the poses; the
            # tie to keyframe 0 stays only as a weak hold (1 m) on an axis no wall face measures
            z[-1] = relative_pose(poses[0], wall_pose[0])
            info[-1, 0, 0] = info[-1, 1, 1] = 1.0
            ei = np.concatenate((ei, np.full(len(lattice_j), wall, dtype=np.intp)))
            ej = np.concatenate((ej, lattice_j)).astype(np.intp)
            z = np.vstack((z, lattice_z))
            info = np.concatenate((info, lattice_info))
    return WallPriors(wall_pose, ei, ej, z, info), fit


def lattice_edges(
    keyframes: Sequence[Keyframe],
    poses: np.ndarray,
    index: np.ndarray,
    reference: float,
    lattice: LatticeParams,
    fit: PitchFit,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The lattice priors of keyframes ``index`` (:mod:`mazebot.slam.wall_lattice`), as wall-vertex edges.

    ``(vertex position (2,), j (P,), z (P, 3), information (P, 3, 3))``: the wall vertex
    moves to a crossing of the lattice's lines, and each edge says where keyframe ``j``
    lies relative to it along the grid's axes (its heading is left to the wall priors:
    no information on it). None if the walls do not fit the lattice ``fit`` found, or no
    keyframe's faces fit it.
    """
    if not fit.fits:
        return None
    # the pitch to a tenth of a millimetre: the keyframes' faces, measured at it, stay cached between jobs;
    # and a prior is worth no more than the walls lie on the lattice (a maze built by hand: boards
    # millimetres off their lines)
    std_m = max(lattice.std_m, math.ceil(fit.line_rms_m * 1000.0) / 1000.0)
    lattice = replace(lattice, pitch_m=round(fit.pitch_m, 4), std_m=std_m)
    faces = [keyframes[k].lattice_faces(float(poses[k, 2]) - reference, lattice) for k in index]
    rows, target, weight, line = lattice_priors(poses[index], faces, poses[0, :2], reference, lattice)
    if not len(rows):
        return None
    c, s = math.cos(reference), math.sin(reference)
    crossing = poses[0, :2] + (c * line[0] - s * line[1], s * line[0] + c * line[1])
    info = np.zeros((len(rows), 3, 3))
    info[:, 0, 0], info[:, 1, 1] = weight[:, 0], weight[:, 1]
    return crossing, index[rows], np.column_stack((target, np.zeros(len(rows)))), info


def lattice_fit(
    keyframes: Sequence[Keyframe], poses: np.ndarray, index: np.ndarray, reference: float, lattice: LatticeParams
) -> PitchFit:
    """The lattice of the faces keyframes ``index`` see (:func:`mazebot.slam.lattice_fit.fit_pitch`).

    Every keyframe's surface points within ``lattice.max_range_m`` of its lidar, in the
    map frame turned onto the wall grid (``reference``), split by the side their normal
    faces (+u, −u, +v, −v: the classes of :data:`mazebot.slam.wall_lattice.FACE_CLASSES`):
    the positions of the walls' faces across themselves.
    """
    cos_tol = math.cos(lattice.normal_tolerance_rad)
    chosen = [int(k) for k in index[:: max(1, len(index) // LATTICE_FIT_KEYFRAMES)]]
    if not chosen:
        return fit_pitch([(np.zeros(0), np.ones(0), part // 2) for part in range(4)], lattice.pitch_m,
                         search=lattice.pitch_search, tolerance_m=lattice.fit_tolerance_m)
    # every chosen keyframe's surface in one array (one numpy call per step, not one per keyframe: a
    # job looks at up to LATTICE_FIT_KEYFRAMES of them); each point keeps its keyframe's index in `owner`
    surfaces = [keyframes[k].surface() for k in chosen]
    counts = [len(pts) for pts, _ in surfaces]
    owner = np.repeat(np.arange(len(chosen)), counts)
    pts = np.concatenate([pts for pts, _ in surfaces])
    nrm = np.concatenate([nrm for _, nrm in surfaces])
    sensor = np.repeat(np.array([keyframes[k].sensor_xy for k in chosen], dtype=np.float64), counts, axis=0)
    near = within_radius(pts[:, 0] - sensor[:, 0], pts[:, 1] - sensor[:, 1], lattice.max_range_m)
    pts, nrm, owner = pts[near].astype(np.float64), nrm[near].astype(np.float64), owner[near]
    # per keyframe, in floats as before: its heading on the grid, and its origin on the grid's axes
    cr, sr = math.cos(reference), math.sin(reference)
    frames = []
    for k in chosen:
        x, y, theta = poses[k]
        frames.append((math.cos(theta - reference), math.sin(theta - reference), cr * x + sr * y, -sr * x + cr * y))
    kept = np.bincount(owner, minlength=len(chosen))  # each keyframe's points within range, in order
    c, s, u0, v0 = (np.repeat(column, kept) for column in np.array(frames, dtype=np.float64).T)
    # its points turned by its heading on the grid, the same arithmetic in the same order
    u = u0 + c * pts[:, 0] - s * pts[:, 1]
    v = v0 + s * pts[:, 0] + c * pts[:, 1]
    nu = c * nrm[:, 0] - s * nrm[:, 1]
    nv = s * nrm[:, 0] + c * nrm[:, 1]
    classes = []
    for part, (position, normal) in enumerate(((u, nu), (u, -nu), (v, nv), (v, -nv))):
        positions = position[normal >= cos_tol]  # faces seen from +u, -u, +v, -v: each its own phase
        classes.append((positions, np.ones(positions.size), part // 2))
    return fit_pitch(classes, lattice.pitch_m, search=lattice.pitch_search, tolerance_m=lattice.fit_tolerance_m)


#: Relative margin of :func:`within_radius`'s squared test: far beyond the rounding of either form.
WITHIN_MARGIN = 1e-9


def within_radius(dx: np.ndarray, dy: np.ndarray, radius: float) -> np.ndarray:
    """``np.hypot(dx, dy) <= radius``, the same booleans at a fraction of the cost.

    ``dx² + dy²`` decides every point clearly inside or outside (a relative margin of
    ``WITHIN_MARGIN`` on the square, far beyond the rounding of either form); only the
    points in the thin band between are given to ``np.hypot``, which is correctly rounded to
    within an ulp but several times slower (2.5 ms for 120 000 points here).
    """
    d2 = dx * dx + dy * dy
    r2 = radius * radius
    inside = d2 <= r2 * (1.0 - WITHIN_MARGIN)
    band = np.flatnonzero((d2 > r2 * (1.0 - WITHIN_MARGIN)) & (d2 <= r2 * (1.0 + WITHIN_MARGIN)))
    if band.size:
        inside[band] = np.hypot(dx[band], dy[band]) <= radius
    return inside
