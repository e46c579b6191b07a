"""One straight wall seen on two passes: a tie across it between the two keyframes.

A keyframe's straight wall faces (:meth:`mazebot.slam.keyframes.Keyframe.wall_faces`) are
segments with the normal of the side the lidar saw. Two keyframes far apart in the chain
(another pass of the robot) that see faces facing the same way, in line to within
``TIE_WINDOW_M`` across and overlapping or nearly meeting along, see one straight wall (or
boards set in line along it): the second face's centre lies on the first one's line. The
tie says only that, one direction across the wall, as an edge between the two keyframes
whose information is ``1 / line_tie_std_m²`` along the first face's normal and nothing
else (its measurement the pair's present relative pose moved across the wall by the gap
between the lines). Faces facing each other's back, overlapping along a board's length and
a board's thickness apart, are the two sides of one board: the tie puts them the boards'
thickness apart, taken as the median depth of such pairs that one stretch of the chain saw
(at least ``BOARD_MIN_PAIRS``; the boards of one maze are assumed alike, not their places).

Why: in a maze, places that meet only across a wall are never in sight of each other, so
no loop closure links them (their candidates are refused as out of sight); a long wall
seen from both sides of a junction of the route, the same boundary wall seen from the two
cells of a wall between them, and above all the one board between them seen from its two
sides, are what they share. The wall lattice
(:mod:`mazebot.slam.wall_lattice`) ties such places through the maze's pitch; these ties
need no pitch and no grid, only that a straight wall stays straight (the line-feature
constraints of line-based SLAM, e.g. Nguyen, Harati, Martinelli, Siegwart & Tomatis,
"Orthogonal SLAM: a step toward lightweight indoor autonomous navigation", IROS 2006,
here between keyframes instead of as landmarks). The heading of the second keyframe
moves its face by its lever arm too; the tie is made again at every optimization from the
present poses, so that first-order part is left to the next one.

The ties join the loop closures in the graph's robust part (dynamic covariance scaling),
so a tie between two walls that only happen to lie in line loses its weight where the
rest of the graph disagrees.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from mazebot.geometry import relative_pose
from mazebot.slam.keyframes import Keyframe

#: Two faces are one wall when their normals agree to within this (a board set by hand is
#: turned by up to about 2° from its neighbours) ...
TIE_ANGLE_RAD = math.radians(3.0)

#: ... the second face's centre lies within this of the first one's line (a wall two chains
#: placed a few centimetres apart; the next wall of a maze is a cell, 18-30 cm, away) ...
TIE_WINDOW_M = 0.04

#: ... and the two segments overlap, or their ends are at most this far apart along the line
#: (a post between two boards in line is 12 mm wide; its ends' hits are thin).
TIE_GAP_M = 0.05

#: Only faces of at least this many points and this half length are tied (a short face is a
#: post's side or a board's end, whose normal is poorly known).
TIE_MIN_POINTS = 20
TIE_MIN_HALF_LENGTH_M = 0.05

#: Faces whose centres lie at most this far apart are compared (the faces' half lengths are mostly
#: 0.1-0.4 m; longer ones are tied through their neighbours).
TIE_REACH_M = 1.0

#: The other side of one board: a face facing the other way, behind the first one by up to this
#: (boards 6-20 mm thick) ...
BOARD_MAX_M = 0.03

#: ... overlapping it along the wall by at least this ...
BOARD_OVERLAP_M = 0.05

#: ... and only once this many such pairs seen within one stretch of the chain (fewer than the
#: passes' keyframes apart) give the boards' thickness (their median depth).
BOARD_MIN_PAIRS = 20

#: Each face of a keyframe is tied to at most this many faces of older passes, the nearest
#: along the line first: one pass's many keyframes see one wall again and again.
TIES_PER_FACE = 2


def line_ties(
    keyframes: Sequence[Keyframe], poses: np.ndarray, std_m: float, min_gap: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ties (module docstring) as pose-graph edges ``(i, j, z, information)``, ``i < j``.

    ``poses`` (K, 3) are the keyframes' present poses; ``min_gap`` the keyframes between the
    two ends at least (another pass: the loop closures' ``min_keyframe_gap``).
    """
    kf_index, centre, normal, half = _placed_faces(keyframes, poses)
    empty = (np.zeros(0, np.intp), np.zeros(0, np.intp), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    if centre.shape[0] < 2:
        return empty
    pairs = cKDTree(centre).query_pairs(TIE_REACH_M, output_type="ndarray")
    if pairs.size == 0:
        return empty
    # the newer keyframe's face is b, the older one's a
    swap = kf_index[pairs[:, 0]] > kf_index[pairs[:, 1]]
    a = np.where(swap, pairs[:, 1], pairs[:, 0])
    b = np.where(swap, pairs[:, 0], pairs[:, 1])
    turn = np.abs(np.remainder(normal[b] - normal[a] + math.pi, math.tau) - math.pi)
    same, opposite = turn <= TIE_ANGLE_RAD, turn >= math.pi - TIE_ANGLE_RAD
    a, b, opposite = a[same | opposite], b[same | opposite], opposite[same | opposite]
    n = np.column_stack((np.cos(normal[a]), np.sin(normal[a])))
    d = centre[b] - centre[a]
    across = np.einsum("ij,ij->i", n, d)
    along = np.abs(n[:, 0] * d[:, 1] - n[:, 1] * d[:, 0])
    gap = along - half[a] - half[b]
    apart = kf_index[b] - kf_index[a]
    in_line = ~opposite & (apart >= min_gap) & (np.abs(across) <= TIE_WINDOW_M) & (gap <= TIE_GAP_M)
    # the other side of one board: behind the first face, the two overlapping along it; the boards'
    # thickness from the pairs one stretch of the chain saw (in the map as it is, two passes' pairs
    # would measure their own misplacement too)
    board = opposite & (-across >= -TIE_WINDOW_M) & (-across <= BOARD_MAX_M + TIE_WINDOW_M)
    board &= (gap <= -BOARD_OVERLAP_M) & (apart > 0)
    same_pass = board & (apart < min_gap)
    behind = board & (apart >= min_gap)
    target = np.zeros(a.size)
    if same_pass.sum() >= BOARD_MIN_PAIRS:
        target[behind] = -float(np.median(-across[same_pass]))
    else:
        behind[:] = False
    keep = in_line | behind
    a, b, n, across, gap, target = a[keep], b[keep], n[keep], across[keep], gap[keep], target[keep]
    if a.size == 0:
        return empty
    # per face b, its TIES_PER_FACE nearest along the line (most overlap first)
    order = np.lexsort((gap, b))
    b_sorted = b[order]
    first = np.r_[True, b_sorted[1:] != b_sorted[:-1]]
    rank = np.arange(order.size) - np.maximum.accumulate(np.where(first, np.arange(order.size), 0))
    chosen = order[rank < TIES_PER_FACE]
    a, b, n, across, target = a[chosen], b[chosen], n[chosen], across[chosen], target[chosen]
    i, j = kf_index[a], kf_index[b]
    # the measurement: j seen from i, moved back across the wall by the gap between the lines (less the
    # board's thickness for its other side)
    # (in the map frame; the edge is in i's frame), heading as it is
    moved = poses[j].copy()
    moved[:, :2] -= (across - target)[:, None] * n
    z = relative_pose(poses[i], moved)
    # information along the wall's normal in the residual's frame (the measurement's, j's)
    m_angle = np.arctan2(n[:, 1], n[:, 0]) - poses[j, 2]
    m = np.column_stack((np.cos(m_angle), np.sin(m_angle)))
    information = np.zeros((a.size, 3, 3))
    information[:, :2, :2] = m[:, :, None] * m[:, None, :] / std_m**2
    return i.astype(np.intp), j.astype(np.intp), z, information


def _placed_faces(
    keyframes: Sequence[Keyframe], poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every keyframe's usable faces in the map frame: (keyframe, centre (F, 2), normal angle, half length)."""
    index, centres, normals, halves = [], [], [], []
    for k, kf in enumerate(keyframes):
        faces = kf.wall_faces()
        if len(faces) == 0:
            continue
        use = (faces.count >= TIE_MIN_POINTS) & (faces.half_length_m >= TIE_MIN_HALF_LENGTH_M)
        if not use.any():
            continue
        placed = faces.placed(poses[k])
        index.append(np.full(int(use.sum()), k))
        centres.append(placed.centre_xy[use])
        normals.append(placed.normal_rad[use])
        halves.append(placed.half_length_m[use])
    if not index:
        return np.zeros(0, np.intp), np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    return np.concatenate(index), np.vstack(centres), np.concatenate(normals), np.concatenate(halves)
