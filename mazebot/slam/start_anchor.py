"""The maze's wall grid as seen from the start of a maze built by hand: every board judged together.

Keyframe 0, the map's anchor, measures the walls it sees while the robot stands still
(:mod:`mazebot.slam.wall_priors`). In a maze built by hand each board stands at its own
small angle (a few tenths of a degree), so the two to four faces seen from the start are
not the maze's grid: anchored to their mean, the whole map turns about the start by their
error; not anchored at all, it keeps whatever turn the cheap robot's first turns left in
the chain of scan matches (:mod:`mazebot.slam.wall_faces` tells the two kinds of maze apart).

Every keyframe sees several faces at once, and the differences of their directions within
one scan do not depend on the keyframe's heading, however wrong. So the faces of all
keyframes are judged together, as a two-way layout (Scheffé, *The Analysis of Variance*,
1959, ch. 4): a face ``f`` seen from place ``o`` (a keyframe, or keyframe 0 at rest) has
the direction, in that place's own frame,

    a_of = g_o + β_s(f)

where ``g_o`` is the maze's mean grid in the frame of ``o`` and ``β_s`` the turn of the
stretch of wall ``s`` the face lies on (a side, a few centimetres across and a cell along,
found where the face lies in the map: the map's errors of a few millimetres and tenths of
a degree do not move a face to another stretch). Least squares over all faces, each
stretch's turn drawn about zero with a board's spread (the maze's grid is where its boards'
turns average out; a ridge, so a stretch seen from few places, at the end of a long chain of
them, cannot wander), gives ``g`` for keyframe 0 at rest: the anchor, in its own frame.
Neither a map turned about the start nor one bent at a corner enters it, only which face
lies on which wall.
None until a face keyframe 0 saw at rest has been seen from another keyframe.

Linked by faces alone, the places reach the boards far from the start only through chains
of faces seen from both ends, each face's reading scattered by ~0.4° (a partial view of a
stretch across two boards in line reads the step between them as a turn): the fit's anchor
stays the start's few boards' (the bench's 8×8 seed 6 kept −0.5 … −0.85° off the maze's grid
at a std of 0.3° through 360 keyframes; Portugal-2024-Final built by hand −0.65° ± 0.42°
from two faces at rest). The pose graph's own edges (the chain of scan matches and the
closures) say how the places' frames turn against each other: with ``links``, every keyframe
is a place and each edge ``i → j`` measuring the turn ``Δθ`` adds ``g_j − g_i = −Δθ`` at the
edge's own heading std, so every board the map has seen counts towards the start's grid as
far as the chain to it holds its heading (the same measurements the pose graph optimises;
a heading-only graph with the stretches as landmarks, solved in closed form).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.sparse import csc_matrix
from scipy.sparse.linalg import spsolve

from mazebot.slam.keyframes import Keyframe
from mazebot.slam.wall_faces import Faces, face_spread, quarter_turns

#: Faces on one side within this across ...
STRETCH_ACROSS_M = 0.05

#: ... and this along (a cell) lie on one stretch of wall: one board, or two in line.
STRETCH_ALONG_M = 0.3

#: A board set by hand stands turned by about this from the maze's grid (RMS): a maker's
#: care with a square and a pencil line (the simulator's hand-built preset draws 0.7°). The
#: prior of each stretch's turn: the maze's grid is where the boards' turns average to zero.
BOARD_TURN_STD_RAD = math.radians(0.7)

#: The faces' std the fit starts from ...
FACE_STD_START_RAD = math.radians(0.2)

#: ... and how often it is estimated again from the residuals (it settles within three rounds on
#: the bench's hand-built mazes: 0.39°, 0.40°, 0.40°).
FACE_STD_ITERATIONS = 3

#: The faces' std is never taken below this (a simulated lidar without noise fits exactly).
FACE_STD_MIN_RAD = math.radians(0.02)


def start_anchor_rad(
    rest: Faces,
    keyframes: Sequence[Keyframe],
    poses: np.ndarray,
    reference_rad: float,
    links: Links | None = None,
) -> tuple[float, float] | None:
    """Keyframe 0's anchor direction in its own frame (modulo 90°), ``g`` at rest (module docstring), and its std.

    The std is the fit's own (its normal matrix's inverse at ``g``): ~0.3° on the bench's
    hand-built 8×8 mazes, where the direction came out 0.02-0.65° off the maze's grid.

    ``rest`` are the faces keyframe 0 saw at rest (its frame), ``poses`` (K, 3) the keyframes'
    current poses and ``reference_rad`` the wall grid's direction in the map as known so far:
    they only place the faces on their stretches. Every keyframe after the first adds its
    faces (:meth:`mazebot.slam.keyframes.Keyframe.wall_faces`, cached). ``links``: the pose
    graph's edges (:func:`heading_links`) between the keyframes; None: the places are linked
    by the faces they share alone.
    """
    places = [rest] + [keyframes[k].wall_faces() for k in range(1, len(keyframes))]
    seen = [place for place, faces in enumerate(places) if len(faces)]  # places without faces left out
    if not seen or seen[0] != 0:
        return None
    faces = Faces.joined([places[place] for place in seen])
    counts = np.array([len(places[place]) for place in seen])
    seen_poses = np.asarray(poses)[seen]
    _, stretch = np.unique(stretch_keys(placed_each(faces, seen_poses, counts), reference_rad),
                           axis=0, return_inverse=True)
    stretch = stretch.reshape(-1)
    if links is None:
        owner = np.repeat(np.arange(len(seen)), counts)  # 0 stays keyframe 0 at rest
        starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
        base = np.repeat(faces.normal_rad[starts], counts)  # each place's first face: one quadrant per place
    else:
        owner = np.repeat(np.asarray(seen), counts)  # every keyframe a place: the links run through those without faces
        # one quadrant per place about the grid as its pose sees it, so that the places' grids differ by their
        # turns, as the links measure them
        base = np.repeat(reference_rad - seen_poses[:, 2], counts)
    if not np.isin(stretch[owner == 0], stretch[owner != 0]).any():
        return None  # nothing keyframe 0 saw has been seen again: its faces alone are no anchor
    turns = None if links is None else _place_turns(links, poses)
    direction, std = _two_way_fit(owner, stretch, base + quarter_turns(faces.normal_rad - base), turns, len(places))
    return float(quarter_turns(np.array([direction]))[0]), std


def start_view_rad(rest: Faces, max_spread_rad: float) -> tuple[float, float] | None:
    """The wall grid as keyframe 0's faces at rest alone put it (its frame, modulo 90°), and the std of that mean.

    Where the start's faces lie on one grid (they turn apart by no more than ``max_spread_rad``,
    RMS: walls set square), each is a reading of the same direction, and their mean, weighted by
    points, is the start's own view of the grid; its std is the standard error of that mean,
    the faces' spread about it over ``n - 1`` degrees of freedom (``spread / sqrt(n - 1)``, the
    spread being the points-weighted RMS about the mean). Pooled over the revolutions at rest,
    those faces read the exact mazes' grid within ~0.1°, where the fit over every keyframe's faces
    (:func:`start_anchor_rad`, which lets each stretch turn by a board's spread) put it 0.2° off at
    a std of 0.16° (the bench's 16×16 scripted seed 18). None with fewer than two faces, or faces
    that turn apart (boards set by hand: their mean is the start's boards', not the maze's).
    """
    if len(rest) < 2:
        return None
    base = float(rest.normal_rad[0])
    turns = quarter_turns(rest.normal_rad - base)
    spread = face_spread(turns, rest.count)
    if spread is None or spread > max_spread_rad:
        return None
    mean = float(np.average(turns, weights=rest.count))
    return float(quarter_turns(np.array([base + mean]))[0]), spread / math.sqrt(len(rest) - 1)


def placed_each(faces: Faces, poses: np.ndarray, counts: np.ndarray) -> Faces:
    """The faces of several places, joined, each place's in the frame where its pose places it.

    ``faces`` are the places' faces joined in order, ``counts`` (P,) how many are each
    place's and ``poses`` (P, 3) the places' poses: the same values as
    :meth:`Faces.placed` place by place, to the bit (each place's cosine and sine from
    ``math``, the same sums in the same order), in one pass over all faces. Judging the
    start's anchor places every keyframe's faces in each loop-closure job, and place by
    place the numpy calls' own overhead cost more than their arithmetic.
    """
    heading = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    c = np.repeat([math.cos(float(t)) for t in heading[:, 2]], counts)
    s = np.repeat([math.sin(float(t)) for t in heading[:, 2]], counts)
    x0, y0, turn = (np.repeat(heading[:, i], counts) for i in range(3))
    x, y = faces.centre_xy[:, 0], faces.centre_xy[:, 1]
    centre = np.column_stack((x0 + c * x - s * y, y0 + s * x + c * y))
    return Faces(centre, faces.normal_rad + turn, faces.half_length_m, faces.count)


#: The pose graph's edges as :func:`start_anchor_rad` takes them: ``(i (E,), j (E,), turn_rad (E,),
#: std_rad (E,))``, each the turn of keyframe ``j``'s frame against ``i``'s and its std.
Links = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def heading_links(
    edges: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], keyframes: int
) -> Links:
    """The heading part of a pose graph's edges ``(i, j, z (E, 3), information (E, 3, 3))`` among ``keyframes``.

    Each edge's std is its information's on the heading alone (the graph's own weight for it);
    edges to vertices beyond the keyframes (none in the graph the loop-closure job is given)
    are left out, and so are edges that carry no heading.
    """
    i, j, z, information = edges
    i, j = np.asarray(i, dtype=np.intp), np.asarray(j, dtype=np.intp)
    heading_information = np.asarray(information)[:, 2, 2] if len(i) else np.zeros(0)
    keep = (i < keyframes) & (j < keyframes) & (i != j) & (heading_information > 0)
    return i[keep], j[keep], np.asarray(z)[keep, 2], 1.0 / np.sqrt(heading_information[keep])


def _place_turns(links: Links, poses: np.ndarray) -> Links:
    """The links as turns between the places' grids: ``g_j - g_i = -Δθ`` (the edge's turn taken the whole
    turns nearest the poses' own difference, so that it compares with the places' quadrants)."""
    i, j, turn, std = links
    between = poses[j, 2] - poses[i, 2]
    whole = np.round((between - turn) / math.tau) * math.tau
    return i, j, -(turn + whole), std


def stretch_keys(faces: Faces, reference_rad: float) -> np.ndarray:
    """Each face's stretch of wall (F, 3): the side its normal faces on the grid, its place across and along."""
    relative = faces.normal_rad - reference_rad
    side = np.round((relative - quarter_turns(relative)) / (math.pi / 2)).astype(np.int64) % 4
    c, s = math.cos(reference_rad), math.sin(reference_rad)
    u = c * faces.centre_xy[:, 0] + s * faces.centre_xy[:, 1]
    v = -s * faces.centre_xy[:, 0] + c * faces.centre_xy[:, 1]
    across_u = side % 2 == 0
    across = np.floor(np.where(across_u, u, v) / STRETCH_ACROSS_M).astype(np.int64)
    along = np.floor(np.where(across_u, v, u) / STRETCH_ALONG_M).astype(np.int64)
    return np.column_stack((side, across, along))


#: With links every keyframe is a place; one with neither faces nor links (none in a chain of
#: matches) would leave the fit singular: its grid is held at 0 by this weight (rad⁻²), a
#: std of a thousand radians, nothing against a face's or a link's.
_UNTIED_PLACE_WEIGHT = 1e-6


def _place_diagonal(places: int, walls: int) -> csc_matrix:
    """The identity on the places' unknowns of the fit (its stretches' left out)."""
    ones = np.ones(places)
    return csc_matrix((ones, (np.arange(places), np.arange(places))), shape=(places + walls, places + walls))


def _two_way_fit(
    owner: np.ndarray, stretch: np.ndarray, direction: np.ndarray, turns: Links | None = None, count: int = 0
) -> tuple[float, float]:
    """``g`` of place 0 from ``direction = g[owner] + β[stretch]`` (module docstring) by least squares, and its std.

    Each stretch's turn has the prior ``0 ± BOARD_TURN_STD_RAD``; each face the same std, which
    is estimated from the fit's own residuals (``FACE_STD_ITERATIONS`` rounds, from
    ``FACE_STD_START_RAD``): a face's direction in its scan errs by the lidar's noise and
    by what the de-skew left of the cheap robot's slip in turns, neither known beforehand.
    ``turns`` (:func:`_place_turns`, ``count`` places) add ``g_j - g_i`` at each link's std.
    """
    places = max(int(owner.max()) + 1, count if turns is not None else 0)
    seen = np.unique(owner).size  # the places with faces: what the residuals' degrees of freedom lose
    walls = int(stretch.max()) + 1
    rows = np.arange(owner.size)
    links = 0 if turns is None else turns[0].size
    link_rows = owner.size + walls + np.arange(links)
    link_w = np.zeros(0) if turns is None else 1.0 / turns[3]
    link_cols = (np.zeros(0, dtype=np.intp),) * 2 if turns is None else (turns[1], turns[0])
    link_target = np.zeros(0) if turns is None else link_w * turns[2]
    face_std = FACE_STD_START_RAD
    for _ in range(FACE_STD_ITERATIONS):
        face_w = np.full(owner.size, 1.0 / face_std)
        design = csc_matrix(
            (np.concatenate((face_w, face_w, np.full(walls, 1.0 / BOARD_TURN_STD_RAD), link_w, -link_w)),
             (np.concatenate((rows, rows, owner.size + np.arange(walls), link_rows, link_rows)),
              np.concatenate((owner, places + stretch, places + np.arange(walls), *link_cols)))),
            shape=(owner.size + walls + links, places + walls),
        )
        target = np.concatenate((face_w * direction, np.zeros(walls), link_target))
        normal = (design.T @ design).tocsc()
        if turns is not None:
            normal = (normal + _UNTIED_PLACE_WEIGHT * _place_diagonal(places, walls)).tocsc()
        solution = spsolve(normal, design.T @ target)
        residual = direction - solution[owner] - solution[places + stretch]
        face_std = max(math.sqrt(float(residual @ residual) / max(1, owner.size - seen)), FACE_STD_MIN_RAD)
    unit = np.zeros(places + walls)
    unit[0] = 1.0
    return float(solution[0]), math.sqrt(float(spsolve(normal, unit)[0]))
