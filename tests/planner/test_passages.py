"""Passages the robot cannot take: the lane check on the local costmap, and recoveries counted per place.

The geometry is exact: a 1 ft corridor (walls as dense points 0.146 m either side of its
centre line) with a table leg (a 2 cm disc) at a known offset from the centre line. The robot
centre keeps the DWA's contact distance (footprint 0.09 m + margin 0.01 m) from every point, so
a lane beside the leg exists exactly when the gap between the leg's surface and the far wall is
wider than twice that distance.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mazebot.planner.dwa import LocalCostmap, LocalPlanner, cells_without_hits
from mazebot.planner.global_path import GridCostmap
from mazebot.planner.passages import across_path_m, first_unreachable, rasterise_segments

GIVE_UPS_CSV = Path(__file__).parent / "data" / "lane_give_ups.csv"
HALF_CORRIDOR_M = 0.146  # 1 ft pitch less a 12 mm wall, halved
LEG_RADIUS_M = 0.01
CONTACT_M = 0.10  # footprint 0.09 m + the DWA's 0.01 m margin


def corridor_with_leg(leg_offset_m: float | None, leg_x_m: float = 0.2) -> np.ndarray:
    """Robot-frame obstacle points: a corridor along +x, and a leg ``leg_offset_m`` left of its centre line."""
    x = np.arange(-0.5, 0.8, 0.005)
    walls = [np.column_stack((x, np.full(x.size, side * HALF_CORRIDOR_M))) for side in (-1.0, 1.0)]
    if leg_offset_m is not None:
        a = np.linspace(0.0, math.tau, 64, endpoint=False)
        walls.append(np.column_stack((leg_x_m + LEG_RADIUS_M * np.cos(a), leg_offset_m + LEG_RADIUS_M * np.sin(a))))
    return np.concatenate(walls)


def path_ahead() -> np.ndarray:
    return np.column_stack((np.arange(0.0, 0.8, 0.02), np.zeros(40)))


def test_a_leg_that_leaves_no_lane_is_found_past_it_and_one_that_leaves_a_lane_is_not() -> None:
    blocked = corridor_with_leg(0.0)  # on the centre line: 0.126 m either side for a 0.2 m body
    k = first_unreachable(LocalCostmap(blocked, footprint_radius_m=0.09), path_ahead(), CONTACT_M)
    assert k is not None
    # the first path point no centre comes near: within a contact distance and the leg's radius of its centre
    assert 0.2 - CONTACT_M - LEG_RADIUS_M <= path_ahead()[k, 0] <= 0.2
    assert first_unreachable(LocalCostmap(corridor_with_leg(None), footprint_radius_m=0.09), path_ahead(),
                             CONTACT_M) is None
    # a leg against the wall leaves the corridor's whole lane: 0.146 - 0.1 either side of the centre line
    wide = corridor_with_leg(HALF_CORRIDOR_M - LEG_RADIUS_M)
    assert first_unreachable(LocalCostmap(wide, footprint_radius_m=0.09), path_ahead(), CONTACT_M) is None


def recorded_give_up(situation: str) -> dict[str, np.ndarray]:
    """One recorded give-up of ``data/lane_give_ups.csv`` (see its README): points by kind, robot frame."""
    rows: dict[str, list[list[float]]] = {}
    for line in GIVE_UPS_CSV.read_text().splitlines():
        if line.startswith("#"):
            continue
        name, kind, *values = line.split(",")
        if name == situation:
            rows.setdefault(kind, []).append([float(v) for v in values])
    return {kind: np.array(values) for kind, values in rows.items()}


def true_surface_points(give_up: dict[str, np.ndarray], step_m: float = 0.001) -> np.ndarray:
    """The simulator's true walls and legs near the robot, as points ``step_m`` apart."""
    points = []
    for x1, y1, x2, y2 in give_up["true_segment"]:
        t = np.linspace(0.0, 1.0, max(2, math.ceil(math.hypot(x2 - x1, y2 - y1) / step_m) + 1))
        points.append(np.column_stack((x1 + t * (x2 - x1), y1 + t * (y2 - y1))))
    for x, y, r in give_up.get("true_leg", np.zeros((0, 3))):
        a = np.linspace(0.0, math.tau, math.ceil(math.tau * r / step_m), endpoint=False)
        points.append(np.column_stack((x + r * np.cos(a), y + r * np.sin(a))))
    return np.concatenate(points)


def dwa_costmap(give_up: dict[str, np.ndarray]) -> LocalCostmap:
    """The costmap the pilot builds for the lane check: scan and graph walls exact, 2 cm map cells as discs."""
    return LocalCostmap(np.concatenate((give_up["scan"], give_up["wall"])), give_up["map"],
                        0.02 * math.sqrt(0.5), footprint_radius_m=0.09)


def test_a_corner_the_body_passes_with_the_margin_is_a_lane_on_the_dwas_own_costmap() -> None:
    """The cheap robot's give-up beside a table leg in the inside corner of a turn (hand-built 8x8, seed 2).

    The true surfaces leave the body 25 mm (the margin 15 mm) at the narrowest; the DWA's own costmap,
    its map cells as discs of half their diagonal, 4.1 mm over the contact distance, in a lane that
    runs diagonally to the robot's grid and is 12 mm wide: centres 1 cm apart and 4-connected split it
    and said "no lane" there, which closed the only way home.
    """
    corner = recorded_give_up("corner")
    path = corner["path"]
    truth = LocalCostmap(true_surface_points(corner), footprint_radius_m=0.09)
    assert first_unreachable(truth, path, CONTACT_M) is None
    assert first_unreachable(dwa_costmap(corner), path, CONTACT_M) is None


def test_a_leg_the_dwas_costmap_leaves_no_lane_past_is_no_lane() -> None:
    """The give-up beside a table leg on the way home that the DWA could not drive past (hand-built 8x8, seed 8).

    The true surfaces would let the body by with 20.7 mm to spare, but the DWA's map cells, discs of
    half their diagonal, leave its centre at best 2.6 mm short of the contact distance: every forward
    arc is inadmissible and the robot stands. The lane check judges the costmap the DWA drives on, so
    it says "no lane" where this robot's planner has none; the first path point it cannot reach is
    the one beside the leg.
    """
    leg = recorded_give_up("leg")
    path = leg["path"]
    truth = LocalCostmap(true_surface_points(leg), footprint_radius_m=0.09)
    assert first_unreachable(truth, path, CONTACT_M) is None
    k = first_unreachable(dwa_costmap(leg), path, CONTACT_M)
    assert k is not None
    leg_xy = leg["true_leg"][np.argmin(np.hypot(leg["true_leg"][:, 0], leg["true_leg"][:, 1])), :2]
    assert math.dist(path[k], leg_xy) <= CONTACT_M + LEG_RADIUS_M + 0.05  # within a lane's reach of the leg


def test_map_cells_taken_as_the_hits_they_hold_leave_the_lane_the_body_has_past_the_leg() -> None:
    """``[planner] hits_replace_cells``: the same give-up beside the leg, each occupied map cell that holds
    a hit of the revolution counted as its hits rather than a disc of half its diagonal.

    At the path points ahead the costmap's clearance is then within 1 cm of the true surfaces' (4.3 mm at
    the median; as discs 12.5 mm short at the median, up to 19.4 mm), and the lane the body has past the
    leg is found.
    """
    leg = recorded_give_up("leg")
    (x, y, theta, origin_x, origin_y, cell_m), = leg["frame"]
    cells = cells_without_hits(leg["map"], leg["scan"], (x, y, theta), (origin_x, origin_y), cell_m)
    assert 0 < cells.shape[0] < leg["map"].shape[0]  # the cells behind the measured faces stay
    costmap = LocalCostmap(np.concatenate((leg["scan"], leg["wall"])), cells, cell_m * math.sqrt(0.5),
                           footprint_radius_m=0.09)
    path = leg["path"]
    ahead = np.all(np.abs(path) < 0.35, axis=1)
    truth = LocalCostmap(true_surface_points(leg), footprint_radius_m=0.09)
    error_m = costmap.clearance_m(path[ahead]) - truth.clearance_m(path[ahead])
    assert np.max(np.abs(error_m)) <= 0.01
    assert np.median(np.abs(error_m)) <= 0.005
    assert first_unreachable(costmap, path, CONTACT_M) is None


def test_recoveries_count_per_place_when_the_path_is_replanned_every_tick() -> None:
    """A way home re-planned every tick gives new waypoints: counted per path, recoveries never ran out.

    A box round the robot (no way out); the path's first waypoint moves by 5 mm every 4 s (40
    ticks: twice the stuck time-out) as a re-planned route's does. The local planner must give up
    after its recoveries all the same.
    """
    t = np.linspace(-0.15, 0.15, 31)
    box = np.concatenate(
        [np.column_stack((np.full(31, e), t)) for e in (-0.15, 0.15)]
        + [np.column_stack((t, np.full(31, e))) for e in (-0.15, 0.15)]
    )
    local = LocalPlanner(stuck_timeout_s=2.0, blocked_timeout_s=0.5, max_recoveries=2)
    x = y = heading = 0.0
    gave_up = False
    for k in range(1200):
        local.set_path([(0.005 * (k // 40 % 2), 0.0), (1.0, 0.0)])
        c, s = math.cos(heading), math.sin(heading)
        rel = box - (x, y)
        pts = np.column_stack((c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]))
        cmd = local.step((x, y, heading), (0.0, 0.0), pts, None, 0.0, 0.1 * k)
        if cmd.give_up:
            gave_up = True
            break
        x += cmd.v_mps * 0.1 * math.cos(heading)
        y += cmd.v_mps * 0.1 * math.sin(heading)
        heading += cmd.w_radps * 0.1
        assert float(np.min(np.hypot(box[:, 0] - x, box[:, 1] - y))) >= 0.09
    assert gave_up, "120 s boxed in with the path re-planned every tick, and the local planner never gave up"


def test_a_closed_segment_is_a_wall_for_the_grid_planner() -> None:
    """Outside a maze a closed passage is a segment across the path, drawn into the grid costmap as a wall.

    A ring of corridors (a 1.0 x 0.6 m box round an inner wall from x 0.24 to 0.76 m at y 0.3 m, 2 cm
    cells): from the east end of the bottom corridor to its west end the short way is straight along
    it; with the bottom corridor closed at its middle the route goes round the top.
    """
    res = 0.02
    grid = np.zeros((30, 50), dtype=np.int8)  # rows: y, 0.6 m; columns: x, 1.0 m; all free
    grid[0, :] = grid[-1, :] = grid[:, 0] = grid[:, -1] = 100  # the outer walls
    grid[15, 12:38] = 100  # the inner wall: corridors 0.22 m wide at both ends of it
    origin = (0.0, 0.0)
    start, goal = (0.85, 0.15), (0.15, 0.15)
    straight = GridCostmap(grid, origin, res, footprint_radius_m=0.09, clearance_m=0.0).plan(start, goal)
    assert straight is not None and max(y for _, y in straight) < 0.3  # along the bottom corridor
    segment = across_path_m(np.array([[0.5, 0.15], [0.45, 0.15], [0.4, 0.15]]), 1)
    closed = rasterise_segments([segment], grid.shape, origin, res)
    assert closed[math.floor(0.15 / res), math.floor(0.45 / res)]
    around = GridCostmap(grid, origin, res, footprint_radius_m=0.09, clearance_m=0.0, closed_cells=closed).plan(
        start, goal
    )
    assert around is not None and max(y for _, y in around) > 0.3  # round the top
