"""The maze's walls lie on a square lattice: a position prior for every keyframe.

A micromouse maze is a square grid of cells of one known pitch (``[planner]
cell_size_m``, 1 ft): every wall's centre line lies on a lattice line ``u ≡ 0 (mod
pitch)`` of the wall grid, and every face the lidar sees lies half a wall thickness off
it. The wall-direction prior (:func:`mazebot.slam.wall_priors.wall_priors`)
uses the grid's direction; this module uses its spacing. A keyframe that sees a wall
face at ``s`` along the grid's ``u`` axis (its own frame, turned onto the grid) says its
own position ``u_k`` satisfies ``u_k + s ≡ b (mod pitch)``, where ``b`` is the offset
of that class of faces (walls seen from their ``+u`` side, ``−u``, ``+v``, ``−v``: four
classes, a wall thickness apart in pairs), estimated from all keyframes together. Which
multiple of the pitch is meant is the one nearest the current estimate: the chain of scan
matches drifts by millimetres to a few centimetres, far less than half a cell.

So every keyframe that sees walls is tied, across the track and (where it sees a wall
ahead or a post) along it, to the one lattice the whole maze shares, instead of only to
its neighbours in the chain: parts of the maze that meet only across a wall, which no
loop closure links, can no longer drift apart, and the lattice's far lines fix the
grid's direction better than any one keyframe's walls. In the graph each prior is an
ordinary edge from the wall vertex (its heading the grid's direction, its position a
crossing of the lattice's lines, estimated with the poses) to the keyframe, whose
information covers only the lattice axes it measured.

The pitch itself is measured from the keyframes' faces
(:func:`mazebot.slam.lattice_fit.fit_pitch`, within ``pitch_search`` of the configured
cell size: a maze built by hand is a few per cent off it), and so are the lattice's
direction (the wall vertex) and its lines (the offsets). A world whose walls do not fit
a lattice (a room: its opposite walls fit any pitch, nothing between them) turns the
priors off as a whole; and where some faces do not fit, the faces of one class do not
agree on an offset across keyframes, and that class gives no prior
(:data:`MIN_CONSISTENCY`). Curved things (posts of a room) give
no face: a class needs points along a straight stretch (``min_extent_m``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mazebot.config import PlannerConfig
from mazebot.slam_config import LatticeSection

_PLANNER = PlannerConfig()  # the maze's pitch, written once in [planner]

#: Classes of wall faces: (axis 0 = u / 1 = v, sign of the face normal along it).
FACE_CLASSES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0))

#: A class of faces gives priors only if the keyframes' offsets agree this well (mean
#: resultant length of their phases; 0.9 allows a spread of ~2 cm at a 1 ft pitch).
MIN_CONSISTENCY = 0.9


@dataclass(frozen=True)
class LatticeParams(LatticeSection):
    """How keyframe wall faces become lattice priors: the ``[slam.lattice]`` section and the maze's pitch.

    The pitch is the planner's cell size (``[planner] cell_size_m``, the one key for the
    maze's 1 ft), measured within ``pitch_search`` of it (``[planner] cell_size_search``;
    0: exactly ``pitch_m``).
    """

    pitch_m: float = _PLANNER.cell_size_m
    pitch_search: float = _PLANNER.cell_size_search


@dataclass(frozen=True)
class LatticeFaces:
    """One keyframe's wall faces, per class of :data:`FACE_CLASSES`, measured at grid heading ``psi_rad``.

    ``offset_m`` (4,) is where the class's faces lie along its axis in the keyframe's
    frame turned by ``psi_rad`` (the keyframe's heading minus the grid's direction);
    ``arm_m`` (4,) its derivative by that heading (so a slightly different heading needs
    no new pass over the points); ``count`` (4,) the inlier points (0: no face).
    """

    psi_rad: float
    offset_m: np.ndarray
    arm_m: np.ndarray
    count: np.ndarray
    pitch_m: float = 0.0  # the pitch the faces were measured at

    def at(self, psi_rad: float) -> np.ndarray:
        """The offsets (4,) at grid heading ``psi_rad`` (first order in the change of heading)."""
        return self.offset_m + math.remainder(psi_rad - self.psi_rad, math.tau) * self.arm_m


def measure_faces(
    points_xy: np.ndarray, normals: np.ndarray, sensor_xy: np.ndarray, psi_rad: float, params: LatticeParams
) -> LatticeFaces:
    """The wall faces of one keyframe's surface (points and normals in its own frame) at grid heading ``psi_rad``."""
    offset, arm, count = np.zeros(4), np.zeros(4), np.zeros(4, dtype=np.int64)
    pts = np.asarray(points_xy, dtype=np.float64).reshape(-1, 2)
    nrm = np.asarray(normals, dtype=np.float64).reshape(-1, 2)
    near = np.hypot(pts[:, 0] - sensor_xy[0], pts[:, 1] - sensor_xy[1]) <= params.max_range_m
    pts, nrm = pts[near], nrm[near]
    c, s = math.cos(psi_rad), math.sin(psi_rad)
    turned = (c * pts[:, 0] - s * pts[:, 1], s * pts[:, 0] + c * pts[:, 1])  # u, v
    turned_nrm = (c * nrm[:, 0] - s * nrm[:, 1], s * nrm[:, 0] + c * nrm[:, 1])
    cos_tol = math.cos(params.normal_tolerance_rad)
    pitch = params.pitch_m
    for k, (axis, sign) in enumerate(FACE_CLASSES):
        members = sign * turned_nrm[axis] >= cos_tol
        if int(members.sum()) < params.min_points:
            continue
        coord = turned[axis][members]
        along = turned[1 - axis][members]
        phase = np.exp(2j * np.pi * coord / pitch).sum()
        centre = pitch * math.atan2(phase.imag, phase.real) / math.tau
        residual = np.remainder(coord - centre + 0.5 * pitch, pitch) - 0.5 * pitch
        keep = np.abs(residual) <= params.inlier_m
        kept = int(keep.sum())
        if kept < params.min_points or float(np.ptp(along[keep])) < params.min_extent_m:
            continue
        offset[k] = centre + float(residual[keep].mean())
        # d(u)/dψ = −v and d(v)/dψ = u for a point turned by ψ
        arm[k] = float(-along[keep].mean()) if axis == 0 else float(along[keep].mean())
        count[k] = kept
    return LatticeFaces(psi_rad, offset, arm, count, pitch)


def lattice_priors(
    poses: np.ndarray,
    faces: list[LatticeFaces | None],
    origin_xy: np.ndarray,
    grid_rad: float,
    params: LatticeParams,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The lattice priors of keyframes at ``poses`` (K, 3): ``(index (P,), target (P, 2), weight (P, 2), line (2,))``.

    ``line`` is where the lattice's lines cross, in the grid's frame (origin ``origin_xy``,
    turned by ``grid_rad``): the walls' centre lines, halfway between the offsets of the
    two classes of faces of each axis. ``target`` is where each keyframe should be,
    along u and v, relative to that crossing; ``weight`` the information of each (0:
    that axis not measured). Rows only for keyframes with at least one prior.
    """
    pitch = params.pitch_m
    count = len(faces)
    offsets = np.zeros((count, 4))
    valid = np.zeros((count, 4), dtype=bool)
    psi = poses[:, 2] - grid_rad
    for k, found in enumerate(faces):
        if found is not None:
            offsets[k] = found.at(float(psi[k]))
            valid[k] = found.count > 0
    c, s = math.cos(grid_rad), math.sin(grid_rad)
    dx, dy = poses[:, 0] - origin_xy[0], poses[:, 1] - origin_xy[1]
    u, v = c * dx + s * dy, -s * dx + c * dy
    position = np.column_stack((u, u, v, v))
    face = position + offsets
    # each class's offset on the lattice, from every keyframe that sees such a face
    phases = np.where(valid, np.exp(2j * np.pi * face / pitch), 0.0)
    total = phases.sum(axis=0)
    seen = valid.sum(axis=0)
    consistent = (seen > 0) & (np.abs(total) >= MIN_CONSISTENCY * np.maximum(seen, 1))
    offset = pitch * np.angle(total) / (2 * np.pi)
    line = np.array([_centre_line(offset[0], offset[1], consistent[0], consistent[1], pitch),
                     _centre_line(offset[2], offset[3], consistent[2], consistent[3], pitch)])
    residual = np.remainder(face - offset + 0.5 * pitch, pitch) - 0.5 * pitch
    use = valid & consistent[None, :] & (np.abs(residual) <= params.gate_m)
    weight = use / params.std_m**2
    target = position - residual - np.repeat(line, 2)[None, :]
    w_u, w_v = weight[:, 0] + weight[:, 1], weight[:, 2] + weight[:, 3]
    t_u = np.where(w_u > 0, (weight[:, 0] * target[:, 0] + weight[:, 1] * target[:, 1]) / np.maximum(w_u, 1e-300), 0.0)
    t_v = np.where(w_v > 0, (weight[:, 2] * target[:, 2] + weight[:, 3] * target[:, 3]) / np.maximum(w_v, 1e-300), 0.0)
    rows = np.flatnonzero((w_u > 0) | (w_v > 0))
    return rows, np.column_stack((t_u, t_v))[rows], np.column_stack((w_u, w_v))[rows], line


def _centre_line(plus_m: float, minus_m: float, plus_seen: bool, minus_seen: bool, pitch_m: float) -> float:
    """Where the walls' centre lines lie (mod pitch) from the offsets of their two classes of faces.

    Faces seen from the ``+`` side lie half a wall thickness above the line, the others
    half below: the line is halfway between them (the short way round the pitch). With
    one class only, its faces stand for the line (a constant offset; it moves nothing).
    """
    if plus_seen and minus_seen:
        gap = math.remainder(plus_m - minus_m, pitch_m)
        return minus_m + 0.5 * gap
    if plus_seen:
        return plus_m
    return minus_m if minus_seen else 0.0
