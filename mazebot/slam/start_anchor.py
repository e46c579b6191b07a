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
from dataclasses import dataclass

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


@dataclass(frozen=True)
class StartFit:
    """What :func:`start_anchor_fit` judged: keyframe 0's grid and std, and how far its boards stand turned."""

    direction_rad: float  # g at rest, keyframe 0's frame, modulo 90°
    std_rad: float  # the fit's own std of it
    # the boards' own turn, estimated from every face (:func:`board_turn_std_rad`); None unless asked for
    board_std_rad: float | None
    # how much of the start's own view's boards' turn the fit's direction carries (Σ_s H_s V_s: H_s the fit's
    # direction's sensitivity to the turn of stretch s, V_s the view's weight on it): their covariance is
    # this times board_std_rad² (the view and the fit read the same boards; :func:`joined_with_view`)
    view_board_share: float | None


def start_anchor_rad(
    rest: Faces,
    keyframes: Sequence[Keyframe],
    poses: np.ndarray,
    reference_rad: float,
    links: Links | None = None,
) -> tuple[float, float] | None:
    """Keyframe 0's anchor direction in its own frame (modulo 90°) and its std: :func:`start_anchor_fit`'s."""
    fit = start_anchor_fit(rest, keyframes, poses, reference_rad, links)
    return None if fit is None else (fit.direction_rad, fit.std_rad)


def start_anchor_fit(
    rest: Faces,
    keyframes: Sequence[Keyframe],
    poses: np.ndarray,
    reference_rad: float,
    links: Links | None = None,
    judge_boards: bool = False,
) -> StartFit | None:
    """Keyframe 0's anchor direction in its own frame (modulo 90°), ``g`` at rest (module docstring), and its std.

    With ``judge_boards`` also the boards' own turn and what the direction carries of the start's
    own view's boards (:class:`StartFit`; what joining that view needs, and only that).

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
    directions = base + quarter_turns(faces.normal_rad - base)
    fit = _two_way_fit(owner, stretch, directions, turns, len(places))
    direction = float(quarter_turns(np.array([fit.direction_rad]))[0])
    if not judge_boards:
        return StartFit(direction, fit.std_rad, None, None)
    board_std = board_turn_std_rad(directions, owner, stretch, fit.residual_rad)
    rest_rows = len(rest)  # keyframe 0 at rest is the first place: its faces the first rows
    walls = int(stretch.max()) + 1
    carried = np.bincount(stretch, weights=fit.sensitivity, minlength=walls)
    viewed = np.bincount(stretch[:rest_rows], weights=rest.count / float(np.sum(rest.count)), minlength=walls)
    return StartFit(direction, fit.std_rad, board_std, float(carried @ viewed))


#: Below this many stretches of wall seen the boards' own turn is mostly the prior's
#: (``BOARD_TURN_STD_RAD``): :func:`board_turn_std_rad` weighs the prior as this many stretches.
BOARD_PRIOR_STRETCHES = 4

#: The median of a chi-square variable of one degree of freedom: the median of ``z**2`` for a
#: standard normal ``z`` (what a robust scale matches the faces' squared deviations to).
_CHI2_1_MEDIAN = 0.454936


def board_turn_std_rad(
    direction_rad: np.ndarray, owner: np.ndarray, stretch: np.ndarray, residual_rad: np.ndarray
) -> float:
    """The boards' own turn (RMS about the maze's grid) as the faces show it, the faces' own scatter taken out.

    ``direction_rad`` (F,) is each face's direction in its place's frame, ``owner`` (F,) its place,
    ``stretch`` (F,) its stretch of wall and ``residual_rad`` (F,) what the two-way fit left of it.
    The differences of the faces' directions within one place do not depend on its heading: a face's
    deviation from the mean of its place's ``k`` faces (on ``k`` stretches) has the variance
    ``(1 - 1/k) (σ_board² + σ_face²)`` (a one-way layout, Scheffé 1959, ch. 7). The faces' own scatter
    ``σ_face`` is the fit's residuals', each scaled by its leverage in the additive two-way layout
    (``1/m + 1/k``, ``m`` the faces on its stretch; a stretch seen once fits its face exactly and says
    nothing of it). Each variance is a median matched to a chi-square of one degree of freedom, so that
    a few faces put on the wrong stretch do not set it (Rousseeuw & Croux, JASA 1993, for medians as
    scale estimators). Near zero on walls set square, ~0.7° on the simulator's boards set by hand. With
    few stretches it is pulled towards a board set by hand (``BOARD_TURN_STD_RAD``, weighed as
    ``BOARD_PRIOR_STRETCHES`` stretches): a start seen from few places trusts its own boards little.
    """
    k, place_mean = _group_counts_means(direction_rad, owner)
    m, _ = _group_counts_means(direction_rad, stretch)
    several = k >= 2
    walls = int(np.unique(stretch[several]).size)
    leverage = 1.0 / m + 1.0 / k
    fitted = several & (m >= 2) & (leverage < MAX_LEVERAGE)
    if not walls or not fitted.any():
        return BOARD_TURN_STD_RAD
    total = _median_variance((direction_rad - place_mean)[several] ** 2 * (k / np.maximum(k - 1.0, 1.0))[several])
    face = _median_variance(residual_rad[fitted] ** 2 / (1.0 - leverage[fitted]))
    prior = BOARD_PRIOR_STRETCHES * BOARD_TURN_STD_RAD**2
    return math.sqrt((prior + walls * max(0.0, total - face)) / (BOARD_PRIOR_STRETCHES + walls))


#: Faces whose leverage in the two-way fit is above this are left out of the faces' scatter: the
#: fit follows them too closely for their residuals to say much.
MAX_LEVERAGE = 0.75


def _group_counts_means(value: np.ndarray, group: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each value's group's size and mean (both (F,))."""
    _, index, count = np.unique(group, return_inverse=True, return_counts=True)
    index = index.reshape(-1)
    mean = np.bincount(index, weights=value) / count
    return count[index], mean[index]


def _median_variance(squared: np.ndarray) -> float:
    """The variance of normal deviations whose squares are ``squared``: their median over χ²₁'s."""
    return float(np.median(squared)) / _CHI2_1_MEDIAN


def joined_with_view(judged: tuple[float, float], view: tuple[float, float], covariance_rad2: float,
                     floor_std_rad: float) -> tuple[float, float]:
    """Two readings of the start's grid ``(direction_rad, std_rad)`` whose errors share ``covariance_rad2``, joined.

    The least-variance weighting of two correlated estimates (Bar-Shalom & Campo, "The effect of the
    common process noise on the two-sensor fused-track covariance", IEEE TAES 1986): the view's weight
    ``(V_j - C) / (V_j + V_v - 2C)`` (within [0, 1]) and the variance that weighting leaves. With ``C = 0``
    the inverse-variance mean; where both read the same boards, the view counts for what it adds, not
    twice. Modulo 90°; the std floored at ``floor_std_rad``.
    """
    judged_var, view_var = judged[1] ** 2, view[1] ** 2
    covariance = min(max(covariance_rad2, 0.0), math.sqrt(judged_var * view_var))
    spread = judged_var + view_var - 2.0 * covariance
    weight = 1.0 if spread <= 0.0 else min(max((judged_var - covariance) / spread, 0.0), 1.0)
    variance = (1 - weight) ** 2 * judged_var + weight**2 * view_var + 2 * weight * (1 - weight) * covariance
    step = float(quarter_turns(np.array([view[0] - judged[0]]))[0])
    direction = float(quarter_turns(np.array([judged[0] + weight * step]))[0])
    return direction, max(math.sqrt(max(variance, 0.0)), floor_std_rad)


def start_view_rad(rest: Faces, max_spread_rad: float, board_std_rad: float = 0.0) -> tuple[float, float] | None:
    """The wall grid as keyframe 0's faces at rest alone put it (its frame, modulo 90°), and the std of that mean.

    Where the start's faces lie on one grid (they turn apart by no more than ``max_spread_rad``,
    RMS: walls set square), each is a reading of the same direction, and their mean, weighted by
    points, is the start's own view of the grid. Its std has two parts. The faces' spread about
    the mean over ``n - 1`` degrees of freedom (``spread / sqrt(n - 1)``, the spread being the
    points-weighted RMS about the mean) is what the faces disagree by. A board's own turn is
    common to every point of its face, and the start's few boards may all stand turned the same
    way, which no spread among them shows: ``board_std_rad / sqrt(boards)``, ``boards`` the
    distinct stretches of wall the faces lie on and ``board_std_rad`` the boards' turn estimated
    from every keyframe's faces (:func:`board_turn_std_rad`: near zero on walls set square, where
    pooled over the revolutions at rest the view reads the grid within ~0.1° and the fit over
    every keyframe's faces put it 0.2° off at a std of 0.16°, the bench's 16×16 scripted seed 18;
    ~0.7° on boards set by hand, whose mean is the start's boards', not the maze's). None with
    fewer than two faces, or faces that turn apart.
    """
    if len(rest) < 2:
        return None
    base = float(rest.normal_rad[0])
    turns = quarter_turns(rest.normal_rad - base)
    spread = face_spread(turns, rest.count)
    if spread is None or spread > max_spread_rad:
        return None
    mean = float(np.average(turns, weights=rest.count))
    boards = int(np.unique(stretch_keys(rest, base + mean), axis=0).shape[0])
    std = math.sqrt(spread**2 / (len(rest) - 1) + board_std_rad**2 / boards)
    return float(quarter_turns(np.array([base + mean]))[0]), std


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


@dataclass(frozen=True)
class _Fit:
    """:func:`_two_way_fit`'s answer: place 0's grid and std, the faces' residuals and weights in it."""

    direction_rad: float
    std_rad: float
    residual_rad: np.ndarray  # (F,): what the fit left of each face's direction
    sensitivity: np.ndarray  # (F,): how much place 0's grid moves with each face's direction


def _two_way_fit(
    owner: np.ndarray, stretch: np.ndarray, direction: np.ndarray, turns: Links | None = None, count: int = 0
) -> _Fit:
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
    gain = spsolve(normal, unit)  # the row of the normal matrix's inverse at place 0's grid
    sensitivity = face_w**2 * (gain[owner] + gain[places + stretch])
    return _Fit(float(solution[0]), math.sqrt(float(gain[0])), residual, sensitivity)
